#include <algorithm>
#include <cctype>
#include <map>
#include <set>
#include <cmath>
#include <iostream>
#include <string>
#include <vector>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet::cli {

namespace {
// The long flags of the running command, recorded by parse().
std::set<std::string>& registered_flags() {
  static std::set<std::string> flags;
  return flags;
}
}  // namespace

std::string flag_or_key(const std::string& key) {
  // The two options whose flag is not their field's name.
  static const std::map<std::string, std::string> renamed = {{"output_role.dir", "out"}, {"experiment.sets", "set"}};
  const auto it = renamed.find(key);
  std::string flag = it != renamed.end() ? it->second : key.substr(key.rfind('.') + 1);
  std::replace(flag.begin(), flag.end(), '_', '-');
  return registered_flags().count(flag) ? "--" + flag : key;
}

const FlagTable<CommonSettings>& common_flags() {
  static const FlagTable<CommonSettings> rows = {
      {"threads", &CommonSettings::threads, "CPU threads (0: the cores other work leaves free)", 0, 1024,
       "0 (the free cores) to 1024"},
  };
  return rows;
}

void add_common(cxxopts::Options& options) {
  add_flags(options, common_flags(), "common");
  options.add_options("common")("h,help", "show this help");
}

namespace {

// A switch given a value (`--force=false`, as scripts write `--force=$FORCE`) is read by its value:
// true/1/yes/on keep it, false/0/no/off drop it before cxxopts counts it (every command reads a
// switch by count), anything else is refused. cxxopts itself counts `--force=false` as given.
std::vector<std::string> switches_by_value(const cxxopts::Options& options, int argc, char** argv) {
  std::set<std::string> switches;
  for (const auto& group : options.groups())
    for (const auto& option : options.group_help(group).options)
      if (option.is_boolean)
        for (const auto& name : option.l) switches.insert(name);
  std::vector<std::string> args;
  bool options_ended = false;
  for (int i = 0; i < argc; ++i) {
    const std::string arg = argv[i];
    options_ended = options_ended || arg == "--";
    const auto eq = arg.find('=');
    if (i == 0 || options_ended || arg.rfind("--", 0) != 0 || eq == std::string::npos ||
        !switches.count(arg.substr(2, eq - 2))) {
      args.push_back(arg);
      continue;
    }
    std::string value = arg.substr(eq + 1);
    std::transform(value.begin(), value.end(), value.begin(), [](unsigned char c) { return std::tolower(c); });
    if (value == "true" || value == "1" || value == "yes" || value == "on") {
      args.push_back(arg.substr(0, eq));
    } else if (!(value == "false" || value == "0" || value == "no" || value == "off")) {
      throw Error(arg.substr(0, eq), "'" + printable(arg.substr(eq + 1)) +
                                         "' is not a switch's value: give true or false (or leave the switch out)");
    }
  }
  return args;
}

}  // namespace

bool parse(cxxopts::Options& options, int argc, char** argv, cxxopts::ParseResult& result) {
  for (const auto& group : options.groups())
    for (const auto& option : options.group_help(group).options)
      for (const auto& name : option.l) registered_flags().insert(name);
  const auto args = switches_by_value(options, argc, argv);
  std::vector<char*> pointers;
  for (const auto& a : args) pointers.push_back(const_cast<char*>(a.c_str()));
  argc = static_cast<int>(pointers.size());
  argv = pointers.data();
  try {
    result = options.parse(argc, argv);
  } catch (const cxxopts::exceptions::incorrect_argument_type& e) {
    // cxxopts names the value, not the option: find the flag it was given to.
    const std::string message = e.what();
    auto quoted = [&](const std::string& v) {  // cxxopts quotes with ‘’ or '' depending on the platform
      return message.find("‘" + v + "’") != std::string::npos || message.find("'" + v + "'") != std::string::npos;
    };
    for (int i = 1; i < argc; ++i) {
      const std::string arg = argv[i];
      const auto eq = arg.find('=');
      const bool attached = arg.rfind("--", 0) == 0 && eq != std::string::npos && quoted(arg.substr(eq + 1));
      const bool next = arg.rfind("--", 0) == 0 && i + 1 < argc && quoted(argv[i + 1]);
      if (attached || next)
        throw Error(arg.substr(0, attached ? eq : std::string::npos),
                    "'" + (attached ? arg.substr(eq + 1) : std::string(argv[i + 1])) +
                        "' is not a valid value for this option");
    }
    throw;
  }
  if (result.count("help")) {
    std::cout << options.help() << std::endl;
    return false;
  }
  if (!result.unmatched().empty()) throw Error("unexpected argument '" + result.unmatched()[0] + "'");
  CommonSettings common;
  read_flags(result, common_flags(), common);
  set_threads(common.threads);
  return true;
}

void require_new_output(const std::filesystem::path& out, bool force,
                        const std::vector<std::filesystem::path>& inputs) {
  std::error_code ec;
  for (const auto& in : inputs)
    if (!in.empty() && std::filesystem::exists(in) && std::filesystem::equivalent(in, out, ec))
      throw Error(out, "is also the input; write to another file (the input is never overwritten, even with --force)");
  if (std::filesystem::is_directory(out)) throw Error(out, "is a folder; give a file name");
  if (std::filesystem::exists(out) && !force) throw Error(out, "already exists; add --force to replace it");
}

const FlagTable<LpipsChoice>& lpips_flags() {
  static const FlagTable<LpipsChoice> rows = {
      {"lpips", &LpipsChoice::backbone,
       "add LPIPS v0.1 with this backbone: alex|vgg (needs torchvision's backbone file and the lpips package's "
       "linear layers; docs/evaluation.md)"},
      {"lpips-dir", &LpipsChoice::directory,
       "folder with the LPIPS files (also searched: models/lpips, ~/.cache/torch/hub/checkpoints)"},
  };
  return rows;
}

const FlagTable<ForceChoice>& force_folder_flags() {
  static const FlagTable<ForceChoice> rows = {
      {"force", &ForceChoice::force,
       "write into an --out folder that holds other output or files flatnet did not write"},
  };
  return rows;
}

void add_lpips(cxxopts::Options& options) { add_flags(options, lpips_flags()); }

std::pair<std::string, LpipsFiles> lpips_from(const cxxopts::ParseResult& r) {
  LpipsChoice chosen;
  read_flags(r, lpips_flags(), chosen);
  if (!r.count("lpips")) return {};
  const auto& name = chosen.backbone;
  require(name == "alex" || name == "vgg", "--lpips", "expected alex or vgg, got '" + printable(name) + "'");
  try {
    return {name, find_lpips_files(parse_lpips_backbone(name), chosen.directory)};
  } catch (const Error& e) {
    std::cerr << "no LPIPS column: " << e.what() << "\n";
    return {};
  }
}

const FlagTable<PrecisionChoice>& precision_flags() {
  static const FlagTable<PrecisionChoice> rows = {
      {"precision", &PrecisionChoice::precision,
       "auto|fp32|bf16: auto is bf16 where the CPU has AMX or AVX512-BF16, else fp32"},
  };
  return rows;
}

void add_precision(cxxopts::Options& options) { add_flags(options, precision_flags()); }

Precision precision_from(const cxxopts::ParseResult& r) {
  PrecisionChoice chosen;
  read_flags(r, precision_flags(), chosen);
  const auto p = resolve_precision(chosen.precision, "--precision");
  if (p == Precision::bf16) request_amx_permission();
  std::cerr << "precision: " << describe_precision(p) << "\n";
  return p;
}

OutputClaim claim_out(const cxxopts::ParseResult& r, const std::filesystem::path& out, const std::string& command,
                      const std::string& settings, const std::string& own_file) {
  OutputRole role;
  role.own_file = own_file;
  role.command = command;
  role.settings = settings;
  role.force = r.count("force") > 0;
  return claim_output_folder(out, role);
}

void add_force_folder(cxxopts::Options& options) { add_flags(options, force_folder_flags()); }

std::vector<std::pair<std::string, std::string>> named_paths(const std::vector<std::string>& items,
                                                             const std::string& flag, bool bare_allowed) {
  std::vector<std::pair<std::string, std::string>> out;
  for (const auto& item : items) {
    const auto eq = item.find('=');
    if (bare_allowed && eq == std::string::npos) {
      out.emplace_back(std::filesystem::path(item).stem().string(), item);
      continue;
    }
    require(eq != std::string::npos && eq > 0 && eq + 1 < item.size(), flag,
            "expects NAME=FILE items, got '" + item + "'");
    out.emplace_back(item.substr(0, eq), item.substr(eq + 1));
  }
  return out;
}

CameraConfig camera_from(const cxxopts::ParseResult& r, const std::string& flag) {
  const std::filesystem::path p =
      r.count(flag) ? std::filesystem::path(r[flag].as<std::string>()) : default_camera_path();
  return load_camera_config(p);
}

}  // namespace flatnet::cli
