#include <iomanip>
#include <iostream>
#include <optional>
#include <sstream>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"
#include "io/dataset.hpp"
#include "io/yaml_text.hpp"
#include "optics/calibrate.hpp"
#include "optics/calibrate_dataset.hpp"
#include "optics/camera_fit.hpp"

namespace flatnet::cli {

namespace {

// `flatnet calibrate --dataset DIR`: the calibration identified from display-capture pairs
// (optics/calibrate_dataset.hpp), written with a camera.yaml beside it and the fit per channel.
int calibrate_from_dataset(const cxxopts::ParseResult& r) {
  const auto camera = camera_from(r);
  const std::filesystem::path out = r["out"].as<std::string>();
  require(out.extension() == ".mat", "--out", "the calibration is a .mat file (FlatNet's layout), got '" + out.string() + "'");
  require_new_output(out, r.count("force") > 0);
  std::vector<Pair> pairs;
  if (r.count("meas-list") || r.count("gt-list")) {  // FlatNet's own list files
    require(r.count("meas-list") && r.count("gt-list"), "--meas-list", "give both --meas-list and --gt-list");
    DatasetLists lists{r["meas-list"].as<std::string>(), r["gt-list"].as<std::string>(), {}};
    if (r.count("root")) lists.root = r["root"].as<std::string>();
    pairs = read_pairs(lists);
  } else {
    const std::filesystem::path dir = r["dataset"].as<std::string>();
    for (const auto& split : {"train", "val"}) {
      const auto lists = split_lists(dir, split);
      if (!std::filesystem::exists(lists.meas_list)) continue;
      const auto part = read_pairs(lists);
      pairs.insert(pairs.end(), part.begin(), part.end());
      if (r["split"].as<std::string>() == split) break;
    }
    require(!pairs.empty(), dir, "holds no train_meas.txt / val_meas.txt lists (FlatNet's layout); or give --meas-list and --gt-list");
  }
  // A simulated camera's truth, for the error printed at the end: read now, so that a missing rig
  // is named before the fit runs.
  std::optional<Calibration> truth;
  if (!camera.rig.empty()) truth = ideal_calibration(load_camera_rig(camera), camera.raw);
  const auto limit = r["limit"].as<int64_t>();
  require(limit >= 0, "--limit", "0 (all) or more");
  if (limit > 0 && static_cast<int64_t>(pairs.size()) > limit) pairs.resize(static_cast<size_t>(limit));
  const auto N = camera.scene_size;
  auto load = [&](int64_t i) {
    const auto& p = pairs[static_cast<size_t>(i)];
    auto gt = read_rgb(p.gt);
    if (gt.size(1) != N || gt.size(2) != N) gt = resize(gt, N, N).clamp(0, 1);
    const auto window = raw_window(load_raw_unit(p.meas, camera.raw), camera.raw);  // {4,rows,cols}
    const double saturated = at_full_scale(window, camera.raw.adc_bits).to(torch::kFloat32).mean().item<double>();
    return CapturePair{without_level(double_centre(window, camera.raw.centring), camera.raw.centring),
                       rgb_to_bayer_planes(srgb_to_linear(gt)), window.mean({1, 2}), saturated};
  };
  DatasetCalibrationOptions o;
  o.iterations = r["iterations"].as<int>();
  o.seed = r["seed"].as<uint64_t>();
  o.cache_bytes = static_cast<int64_t>(r["cache-mb"].as<double>() * (1 << 20));
  require(o.iterations >= 1 && o.cache_bytes >= 0, "calibrate", "--iterations >= 1 and --cache-mb >= 0");
  const auto structure = r["structure"].as<std::string>();
  require(structure == "shift" || structure == "free", "calibrate",
          "--structure is shift (a FlatCam's shadow moves with the scene) or free, not '" + structure + "'");
  o.structure = structure == "shift" ? FactorStructure::Shift : FactorStructure::Free;
  std::cerr << "calibrate: " << pairs.size() << " display-capture pairs, " << camera.raw.crop[2] << "x"
            << camera.raw.crop[3] << " planes, " << N << "x" << N << " scenes\n";
  const auto fit = calibrate_from_pairs(static_cast<int64_t>(pairs.size()), load, camera.raw.crop[2],
                                        camera.raw.crop[3], N, o);
  save_calibration(out, fit.calib);
  // A camera.yaml beside it: the geometry given, with this calibration (and no rig: a camera known
  // only from its data).
  auto known = camera;
  known.rig.clear();
  known.noise_gain = fit.noise_gain, known.noise_floor = fit.noise_floor, known.dark = fit.dark;
  known.fit_threshold = fit.fit_threshold;
  known.leak_threshold = fit.leak_threshold;
  const auto yaml_path = out.parent_path() / "camera.yaml";
  std::ostringstream fit_text;
  fit_text << "# identified by `flatnet calibrate --dataset` from " << fit.pairs << " display-capture pairs, "
           << fit.iterations << " alternating steps; relative fit residual per channel (b, gb, gr, r):";
  for (const double v : fit.residual) fit_text << " " << std::setprecision(4) << v;
  if (o.structure == FactorStructure::Shift && !fit.structure_rejected)
    fit_text << "\n# the shadow moves " << std::setprecision(6) << fit.shift_rows << " sensor pixels per scene row, "
             << fit.shift_cols << " per scene column";
  write_text_atomically(yaml_path, fit_text.str() + "\n" + camera_geometry_yaml(known) +
                                       "calibration: " + yaml_quoted(out.filename().string()) + "\n");
  std::cout << "wrote " << out.string() << " and " << yaml_path.string() << " from " << fit.pairs << " pairs ("
            << fit.iterations << " steps)\nfit residual ||Y - P X Q^T - s a b^T|| / ||Y||:";
  for (int c = 0; c < 4; ++c) std::cout << " " << kChannelNames[c] << " " << std::setprecision(4) << fit.residual[c];
  std::cout << "\nsensor noise: variance " << fit.noise_gain << " x (level - " << fit.dark << ") + " << fit.noise_floor
            << " (full well about " << (fit.noise_gain > 0 ? 1 / fit.noise_gain : 0) << " electrons)\ncamera fit: its own pairs"
            << " fit up to the threshold " << fit.fit_threshold;
  if (fit.leak_threshold > 0) std::cout << " and leak up to " << fit.leak_threshold;
  std::cout << ", written to the camera file (this calibration's error is part of what it leaves outside its span)\n";
  if (fit.structure_rejected)
    std::cout << "shift structure rejected: it explains " << std::setprecision(3) << fit.structure_explains
              << " of what free factors explain (a mask that is not one moving shadow?); free factors were fitted, "
                 "which need thousands of pairs\n";
  else if (o.structure == FactorStructure::Shift)
    std::cout << "shift structure: the shadow moves " << std::setprecision(6) << fit.shift_rows
              << " sensor pixels per scene row, " << fit.shift_cols << " per scene column; it explains "
              << std::setprecision(3) << fit.structure_explains << " of what free factors explain\n";
  if (truth) {  // a simulated camera: how close to its true response
    const auto err = calibration_error(fit.calib, *truth);
    std::cout << "relative error against the rig's true response: P " << 100 * err.p << " %, Q " << 100 * err.q
              << " %, forward model " << 100 * err.forward << " %\n";
  }
  return 0;
}

}  // namespace

int calibrate(int argc, char** argv) {
  cxxopts::Options o("flatnet calibrate",
                     "FlatCam calibration (Asif et al. 2017) from separable Hadamard pattern captures.\n"
                     "  simulated:  flatnet calibrate --rig RIG.mat|CAMERA.yaml --out calib.mat\n"
                     "  real:       flatnet calibrate --write-patterns DIR   (show each, capture it as DIR2/NAME.png)\n"
                     "              flatnet calibrate --captures DIR2 --camera CAMERA.yaml --out calib.mat\n"
                     "  from data:  flatnet calibrate --dataset DIR --camera GEOMETRY.yaml --out calib.mat\n"
                     "              (display-capture pairs in FlatNet's layout, or --meas-list/--gt-list [--root])");
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
  o.add_options("from display-capture pairs")(
      "dataset", "dataset folder in FlatNet's layout (train_meas.txt, train_gt.txt, ...)", cxxopts::value<std::string>())(
      "meas-list", "FlatNet's own capture list (with --gt-list)", cxxopts::value<std::string>())(
      "gt-list", "FlatNet's own photograph list", cxxopts::value<std::string>())(
      "root", "folder the lists' lines are relative to (default: the lists' folder)", cxxopts::value<std::string>())(
      "split", "train (the train list only) or all (train and val)", cxxopts::value<std::string>()->default_value("train"))(
      "limit", "use the first N pairs (0: all)", cxxopts::value<int64_t>()->default_value("0"))(
      "iterations", "alternating least-squares steps at most", cxxopts::value<int>()->default_value("40"))(
      "structure", "shift: each factor's columns are one profile moved by a shift found from the data (a FlatCam's "
      "shadow; few pairs suffice); free: every entry free (any separable camera; needs many pairs)",
      cxxopts::value<std::string>()->default_value("shift"))(
      "cache-mb", "decoded pairs kept in memory (the rest are re-read each pass)",
      cxxopts::value<double>()->default_value("2048"));
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
  require(r.count("rig") + r.count("captures") + (r.count("dataset") || r.count("meas-list")) == 1, "calibrate",
          "give exactly one of --rig, --captures or --dataset (--meas-list)");
  require(r["split"].as<std::string>() == "train" || r["split"].as<std::string>() == "all", "--split",
          "expected train or all");
  if (r.count("dataset") || r.count("meas-list")) return calibrate_from_dataset(r);
  const std::filesystem::path out = r["out"].as<std::string>();
  require_new_output(out, r.count("force") > 0);

  Calibration est;
  std::optional<Calibration> truth;
  if (r.count("rig")) {
    const auto camera = load_camera_config(r["rig"].as<std::string>());
    require(!camera.rig.empty(), r["rig"].as<std::string>(), "names no rig to simulate with");
    const auto rig = load_camera_rig(camera);
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
