#include <iostream>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"
#include "optics/calibrate.hpp"

namespace flatnet::cli {

int calibrate(int argc, char** argv) {
  cxxopts::Options o("flatnet calibrate",
                     "FlatCam calibration (Asif et al. 2017) from separable Hadamard pattern captures.\n"
                     "  simulated:  flatnet calibrate --rig RIG.mat|CAMERA.yaml --out calib.mat\n"
                     "  real:       flatnet calibrate --write-patterns DIR   (show each, capture it as DIR2/NAME.png)\n"
                     "              flatnet calibrate --captures DIR2 --camera CAMERA.yaml --out calib.mat");
  o.add_options()("rig", "simulate the captures with this rig (.mat) or camera (.yaml)", cxxopts::value<std::string>())(
      "captures", "folder of real captures, one PNG per pattern name", cxxopts::value<std::string>())(
      "write-patterns", "write the pattern images for display into this folder and stop",
      cxxopts::value<std::string>())("camera", "camera .yaml for --captures (geometry, preprocessing)",
                                     cxxopts::value<std::string>())("out", "calibration .mat to write (FlatNet layout)",
                                                                    cxxopts::value<std::string>())(
      "force", "replace an existing --out file")("average", "frames averaged per pattern (simulated)",
                                                 cxxopts::value<int>()->default_value("4"))(
      "noise", "on|off (simulated)", cxxopts::value<std::string>()->default_value("on"))(
      "seed", "noise seed (simulated)", cxxopts::value<uint64_t>()->default_value("0"))(
      "level", "display code (sRGB, 1..255) of the patterns' bright parts",
      cxxopts::value<int>()->default_value(std::to_string(kDefaultPatternLevel)));
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  const int level = r["level"].as<int>();

  if (r.count("write-patterns")) {
    const auto camera = camera_from(r);
    const std::filesystem::path dir = r["write-patterns"].as<std::string>();
    const auto claim = claim_out(r, dir, "calibrate --write-patterns");
    std::string list;
    for (const auto& p : calibration_patterns(camera.scene_size, level)) {
      write_rgb8(dir / (p.name + ".png"), p.image.unsqueeze(0).expand({3, -1, -1}));
      list += p.name + ".png\n";
    }
    write_text_atomically(dir / "patterns.txt", list);
    std::cout << "wrote " << 4 * camera.scene_size << " patterns to " << dir.string()
              << " (show each full screen, capture it, save the raw frame under the same name)\n";
    return 0;
  }
  require(r.count("out"), "calibrate", "--out FILE.mat is required");
  require(r.count("rig") + r.count("captures") == 1, "calibrate", "give exactly one of --rig or --captures");
  const std::filesystem::path out = r["out"].as<std::string>();
  require_new_output(out, r.count("force") > 0);

  Calibration est;
  std::optional<Calibration> truth;
  if (r.count("rig")) {
    const auto camera = load_camera_config(r["rig"].as<std::string>());
    require(!camera.rig.empty(), r["rig"].as<std::string>(), "names no rig to simulate with");
    const auto rig = load_rig(camera.rig);
    const bool noise = r["noise"].as<std::string>() == "on";
    const int average = std::max(1, r["average"].as<int>());
    auto capture = rig_pattern_capture(rig, camera.raw, level, noise, average,
                                       at::detail::createCPUGenerator(r["seed"].as<uint64_t>()));
    est = estimate_calibration(camera.scene_size, capture, level);
    truth = ideal_calibration(rig, camera.raw);
  } else {
    const auto camera = camera_from(r);
    const std::filesystem::path dir = r["captures"].as<std::string>();
    require(std::filesystem::is_directory(dir), dir, "captures folder not found");
    auto capture = [&](const std::string& name) { return load_centred_planes(dir / (name + ".png"), camera.raw); };
    est = estimate_calibration(camera.scene_size, capture, level);
  }
  save_calibration(out, est);
  std::cout << "wrote " << out.string() << " (P1b..P1r " << est.P.size(1) << "x" << est.P.size(2) << ", Q1b..Q1r "
            << est.Q.size(1) << "x" << est.Q.size(2) << ")\n";
  if (truth) {
    const auto err = calibration_error(est, *truth);
    std::cout << "relative error against the rig's true response: P " << 100 * err.p << " %, Q " << 100 * err.q
              << " %, forward model " << 100 * err.forward << " %\n";
  }
  return 0;
}

}  // namespace flatnet::cli
