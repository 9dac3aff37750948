#include <iostream>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet::cli {

void add_common(cxxopts::Options& options) {
  options.add_options("common")("threads", "CPU threads (default: all cores)", cxxopts::value<int>()->default_value("0"))(
      "h,help", "show this help");
}

bool parse(cxxopts::Options& options, int argc, char** argv, cxxopts::ParseResult& result) {
  result = options.parse(argc, argv);
  if (result.count("help")) {
    std::cout << options.help() << std::endl;
    return false;
  }
  if (!result.unmatched().empty()) throw Error("unexpected argument '" + result.unmatched()[0] + "'");
  set_threads(result["threads"].as<int>());
  return true;
}

std::vector<std::string> set_overrides(const cxxopts::ParseResult& r) {
  return r.count("set") ? r["set"].as<std::vector<std::string>>() : std::vector<std::string>{};
}

void add_precision(cxxopts::Options& options) {
  options.add_options()("precision", "auto|fp32|bf16: auto is bf16 where the CPU has AMX or AVX512-BF16, else fp32",
                        cxxopts::value<std::string>()->default_value("auto"));
}

Precision precision_from(const cxxopts::ParseResult& r) {
  const auto p = resolve_precision(r["precision"].as<std::string>(), "--precision");
  if (p == Precision::bf16) request_amx_permission();
  std::cerr << "precision: " << describe_precision(p) << "\n";
  return p;
}

CameraConfig camera_from(const cxxopts::ParseResult& r, const std::string& flag) {
  const std::filesystem::path p = r.count(flag) ? std::filesystem::path(r[flag].as<std::string>()) : default_camera_path();
  return load_camera_config(p);
}

}  // namespace flatnet::cli
