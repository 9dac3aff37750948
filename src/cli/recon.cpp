#include <iostream>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "eval/report.hpp"
#include "recon/run.hpp"

namespace flatnet::cli {

int recon(int argc, char** argv) {
  cxxopts::Options o("flatnet recon", "Reconstruct raw captures with a classical method.");
  o.add_options()("method", "tikhonov | tv", cxxopts::value<std::string>()->default_value("tikhonov"))(
      "camera", "camera .yaml (default: the reference camera)", cxxopts::value<std::string>())(
      "calib", "calibration .mat (default: the camera's)", cxxopts::value<std::string>())(
      "input", "raw capture PNG or folder of them", cxxopts::value<std::string>())(
      "out", "output folder", cxxopts::value<std::string>())(
      "lambda", "regularisation weight (default: the camera file's)", cxxopts::value<double>()->default_value("0"))(
      "batch", "captures per batch", cxxopts::value<int>()->default_value("8"));
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("input") && r.count("out"), "recon", "--input DIR|FILE and --out DIR are required");
  const auto camera = camera_from(r);
  const std::filesystem::path calib_path = r.count("calib") ? std::filesystem::path(r["calib"].as<std::string>()) : camera.calibration;
  require(!calib_path.empty(), "recon", "no calibration: pass --calib or use a camera file that names one");
  const auto calib = load_calibration(calib_path, camera);
  ReconOptions opt;
  opt.method = r["method"].as<std::string>();
  opt.lambda = r["lambda"].as<double>();
  opt.out = r["out"].as<std::string>();
  opt.batch = std::max(1, r["batch"].as<int>());
  const auto captures = collect_captures(r["input"].as<std::string>());
  const auto rep = reconstruct_files(camera, calib, captures, opt);
  std::cout << opt.method << ": " << rep.count << " captures -> " << opt.out.string() << " ("
            << rep.recon_ms_per_capture << " ms per capture reconstruction, " << rep.seconds << " s in all)\n";
  return 0;
}

int eval(int argc, char** argv) {
  cxxopts::Options o("flatnet eval", "PSNR and SSIM of reconstructions against ground truth.");
  o.add_options()("gt", "ground-truth folder", cxxopts::value<std::string>())(
      "out", "reconstructions: a folder of PNGs, or of one subfolder per method; reports are written here",
      cxxopts::value<std::string>())("sheet-rows", "images in the contact sheet", cxxopts::value<int>()->default_value("6"));
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("gt") && r.count("out"), "eval", "--gt DIR and --out DIR are required");
  EvalOptions opt{r["gt"].as<std::string>(), r["out"].as<std::string>(), r["sheet-rows"].as<int>()};
  const auto scores = evaluate(opt);
  std::cout << format_table(scores) << "wrote " << (opt.out / "metrics.csv").string() << " and "
            << (opt.out / "sheet.png").string() << "\n";
  return 0;
}

}  // namespace flatnet::cli
