#include <algorithm>
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
#include "optics/calibrate_references.hpp"
#include "optics/separable_inverse.hpp"
#include "optics/camera_fit.hpp"
#include "optics/hot_pixels.hpp"
#include "optics/reference_camera.hpp"
#include "optics/rotation_estimate.hpp"

namespace flatnet::cli {

namespace {

// The settings of `flatnet calibrate` that have a default (the rest are files and folders); each
// default is the library's where one exists.
struct CalibrateSettings {
  int average = 4;           // frames averaged per pattern (simulated)
  std::string noise = "on";  // on|off (simulated)
  uint64_t seed = 0;
  int level = kDefaultPatternLevel;
  std::string split = "train";
  int64_t limit = 0;
  int iterations = DatasetCalibrationOptions{}.iterations;
  std::string structure = "shift";
  std::string colour_mix = "identify";
  std::string rotation = "estimate";
  double cache_mb = static_cast<double>(DatasetCalibrationOptions{}.cache_bytes >> 20);
  std::string reference_order = "rgb";
  double reference_lambda = 3e-4;
  double min_shift = ReferenceCalibrationOptions{}.shift.min_shift;
  double max_shift = ReferenceCalibrationOptions{}.shift.max_shift;
  double white_light = 1;
  double scene_light = kTypicalSceneLight;
  std::string fixed_light = ReferenceCalibrationOptions{}.fixed_light ? "on" : "off";
  std::string shared_mask = ReferenceCalibrationOptions{}.shared_mask ? "on" : "off";
  int mask_taps = ReferenceCalibrationOptions{}.mask_taps;
  // Files and switches (no default): what to calibrate from, and where the calibration goes.
  std::filesystem::path rig, captures, write_patterns, camera, out;
  bool force = false;
  std::filesystem::path dataset, meas_list, gt_list, root;  // display-capture pairs
  bool references = false, compact = false;                 // from a few captures and reconstructions
  std::filesystem::path white_capture;
};

// The camera.yaml written beside a calibration made from data: the geometry given, with this
// calibration and no rig (a camera known only from its data), under a comment saying how it was made.
struct CameraBeside {
  std::filesystem::path path;
  std::string text;
};
// Read back as `recon` and `train` will read it, before anything is written: flatnet never writes a
// camera file it refuses to read (`why` says what set the value refused).
CameraBeside camera_beside(const std::filesystem::path& calibration, const CameraConfig& known,
                           const std::string& comment, const std::string& why) {
  const auto path = calibration.parent_path() / "camera.yaml";
  try {
    return {path, camera_file_text(known, calibration.filename().string(), comment, path)};
  } catch (const Error& e) {
    throw Error("calibrate", "the camera file this calibration makes would be refused when read (" +
                                 std::string(e.what()) + ")" + why + "; nothing was written");
  }
}

// The references' planes {4,N,N} (b, gb, gr, r) from an 8- or 16-bit RGB reconstruction, in its own
// units (someone else's reconstruction is not sRGB-encoded light: the gain and offset per pair absorb
// its scaling). `order` says which file channel holds red.
torch::Tensor reference_planes(const std::filesystem::path& path, int64_t N, const std::string& order) {
  auto rgb = read_rgb(path);  // {3,H,W}
  if (order == "bgr") rgb = rgb.flip(0);
  if (rgb.size(1) != N || rgb.size(2) != N) rgb = resize(rgb, N, N).clamp(0, 1);
  return rgb_to_bayer_planes(rgb);
}

void print_held_out(const std::vector<HeldOutPair>& held) {
  std::cout << "leave-one-out: each pair reconstructed (Tikhonov) from a calibration of the others, Pearson "
               "correlation with its reference (pixels clipped at zero left out)\n"
            << "  pair                  b      gb     gr     r      shifts (rows, cols)   from the whole calibration "
               "(P, Q, coded light)\n";
  for (const auto& h : held) {
    std::cout << "  " << std::left << std::setw(20) << printable(h.name).substr(0, 20) << std::right << std::fixed
              << std::setprecision(3);
    for (const double c : h.correlation) std::cout << " " << std::setw(6) << c;
    std::cout << "   " << std::setprecision(4) << h.shift_rows << ", " << h.shift_cols;
    if (h.change_p >= 0)
      std::cout << "   " << std::setprecision(3) << h.change_p << ", " << h.change_q << ", " << h.change_coded;
    std::cout << "\n";
    std::cout.unsetf(std::ios::fixed);
  }
}

// `flatnet calibrate --meas-list M --gt-list R --references`: a handful of direct captures and
// someone else's reconstructions of them (optics/calibrate_references.hpp).
// A pair listed twice (the same files, or a capture with the same pixels under another name) would
// be fitted twice and, worse, "held out" while still among the calibration pairs: refused, named.
void require_distinct_pairs(const std::vector<Pair>& pairs, const std::vector<ReferencePair>& refs) {
  std::error_code ec;
  for (size_t i = 0; i < pairs.size(); ++i)
    for (size_t j = 0; j < i; ++j) {
      const bool same_file = std::filesystem::equivalent(pairs[i].meas, pairs[j].meas, ec) ||
                             std::filesystem::equivalent(pairs[i].gt, pairs[j].gt, ec);
      const bool same_pixels =
          torch::equal(refs[i].meas, refs[j].meas) || torch::equal(refs[i].reference, refs[j].reference);
      if (same_file || same_pixels)
        throw Error(pairs[i].meas, std::string("repeats pair ") + std::to_string(j + 1) + " (" +
                                       printable(pairs[j].meas.string()) + ", " + printable(pairs[j].gt.string()) +
                                       (same_file ? "): the same file" : "): the same pixels") +
                                       "; list each capture once (a repeated pair would be held out while still "
                                       "fitted, and its leave-one-out score would mean nothing)");
    }
}

// A capture preprocessed as the reference pairs are (rotation, crop, double-centring, no level), with
// its window's level and saturated share (the noise model's sample).
NoiseSample capture_sample(const std::filesystem::path& path, const CameraConfig& camera) {
  const auto window = raw_window(load_raw_unit(path, camera.raw), camera.raw);  // {4,rows,cols}
  return {without_level(double_centre(window, camera.raw.centring), camera.raw.centring), window.mean({1, 2}),
          at_full_scale(window, camera.raw.adc_bits).to(torch::kFloat32).mean().item<double>()};
}

// --white-capture FILE [--white-light E]: a capture of a uniform white scene, read before any fit (a
// saturated or foreign frame is named at once, not after the calibration's minutes).
std::optional<WhiteCaptureInput> white_capture_of(const cxxopts::ParseResult& r, const CalibrateSettings& s,
                                                  const CameraConfig& camera) {
  if (!r.count("white-capture")) return std::nullopt;
  return WhiteCaptureInput{s.white_capture.string(), s.white_light, capture_sample(s.white_capture, camera)};
}

void print_light_unit(const LightUnit& unit) {
  if (unit.source == LightUnitSource::white_capture) {
    std::cout << "light unit: " << printable(std::filesystem::path(unit.white_name).filename().string()) << " (light "
              << unit.light << ") reads, in the references' units,";
    for (size_t c = 0; c < 4; ++c) std::cout << " " << kChannelNames[c] << " " << std::setprecision(4) << unit.level[c];
    std::cout << " (a uniform scene leaves " << std::setprecision(3) << unit.white_residual
              << " of its well-measured coded light): the calibration is in the scene's light\n";
  } else if (unit.source == LightUnitSource::scene_prior) {
    std::cout << "light unit: the pairs' scenes are taken to hold " << unit.light
              << " of the display's white on average (--scene-light; the references' units x " << std::setprecision(4)
              << unit.scale[0] << "): pictures through it are as bright as such scenes, whatever the references' "
              << "stretch; --white-capture measures the light instead (docs/own-camera.md, \"The light unit\")\n";
  } else if (unit.no_scene_light) {
    std::cout << "light unit: a pair's scene has no positive mean light in the references' units; the "
                 "calibration stays in them (--white-capture sets the scene's light)\n";
  }
}

// Why a camera file this calibration makes would be refused: the light unit scales the calibration,
// and its absolute regulariser with the square of that.
std::string light_unit_why(const ReferenceCamera& cam) {
  std::ostringstream why;
  if (cam.light.source == LightUnitSource::white_capture)
    why << ": the light unit from the white capture (--white-light " << cam.light.light << ") puts tikhonov_lambda at "
        << cam.camera.tikhonov_lambda;
  else if (cam.light.source == LightUnitSource::scene_prior)
    why << ": the light unit --scene-light " << cam.light.light << " puts tikhonov_lambda at "
        << cam.camera.tikhonov_lambda << " (a typical photograph holds " << kTypicalSceneLight
        << " of the display's white)";
  return why.str();
}

void print_reference_camera(const ReferenceCamera& cam, const std::filesystem::path& out,
                            const std::filesystem::path& yaml) {
  const auto& fit = cam.fit;
  std::cout << "wrote " << out.string() << " and " << yaml.string() << "\nshift structure: the shadow moves "
            << std::setprecision(6) << fit.shift_rows << " sensor pixels per scene row, " << fit.shift_cols
            << " per scene column\nfit residual ||Y - P (a R + b) Q^T|| / ||Y||:";
  for (int c = 0; c < 4; ++c) std::cout << " " << kChannelNames[c] << " " << std::setprecision(4) << fit.residual[c];
  std::cout << "\n";
  if (cam.light.source == LightUnitSource::references)
    std::cout << "the calibration is in the references' units: pictures through it are as bright as they are; "
                 "--white-capture sets the scene's light (docs/own-camera.md, \"The light unit\"); if they are "
                 "not linear light (a tone-mapped picture), set the camera file's display_gamma before training "
                 "through it (\"The references' tone\")\n";
  const auto& noise = cam.noise;
  if (!noise.found) {
    std::cout << "no noise model: it needs 2 captures or more whose noise grows with their light; the camera fit "
                 "cannot judge this camera's captures until noise_gain, noise_floor and dark are in its file\n";
    return;
  }
  std::cout << "sensor noise: variance " << noise.noise_gain << " x (level - " << noise.dark << ") + "
            << noise.noise_floor << "; open light " << cam.camera.open_light
            << " x the scene's mean\ncamera fit: the captures' own fits";
  for (const double f : noise.fits) std::cout << " " << std::setprecision(3) << f;
  std::cout << ", threshold " << noise.fit_threshold;
  if (cam.camera.leak_threshold > 0)
    std::cout << ", leak up to " << cam.camera.leak_threshold << " (held-out captures leak up to " << cam.held_leak
              << ")";
  std::cout << " (written to the camera file)\n";
}

// Parses and reads; optics/reference_camera.hpp decides.
int calibrate_from_reference_pairs(const cxxopts::ParseResult& r, const CalibrateSettings& s,
                                   const CameraConfig& camera, const std::vector<Pair>& pairs,
                                   const std::filesystem::path& out) {
  const auto order = s.reference_order;
  require(order == "rgb" || order == "bgr", "--reference-order", "rgb or bgr, not '" + printable(order) + "'");
  ReferenceCameraOptions o;
  o.lambda = s.reference_lambda;
  o.scene_light = s.scene_light;
  require(s.fixed_light == "on" || s.fixed_light == "off", "--fixed-light",
          "on or off, not '" + printable(s.fixed_light) + "'");
  o.fit.fixed_light = s.fixed_light == "on";
  require(s.shared_mask == "on" || s.shared_mask == "off", "--shared-mask",
          "on or off, not '" + printable(s.shared_mask) + "'");
  o.fit.shared_mask = s.shared_mask == "on";
  o.fit.mask_taps = s.mask_taps;
  o.fit.seed = s.seed;
  o.fit.shift.min_shift = s.min_shift;
  o.fit.shift.max_shift = s.max_shift;
  std::vector<ReferencePair> refs;
  std::vector<NoiseSample> samples;
  for (const auto& p : pairs) {
    samples.push_back(capture_sample(p.meas, camera));
    refs.push_back({p.meas.filename().string(), samples.back().meas, reference_planes(p.gt, camera.scene_size, order)});
  }
  require_distinct_pairs(pairs, refs);
  const auto white = white_capture_of(r, s, camera);
  std::cerr << "calibrate: " << refs.size() << " captures with reference reconstructions (" << order
            << "), shifts searched from " << o.fit.shift.min_shift << " to " << o.fit.shift.max_shift << " both ways\n";
  const auto cam = identify_reference_camera(refs, samples, white, camera, o);
  if (cam.held.empty())
    std::cout << "leave-one-out needs 3 pairs or more: the calibration is not checked on held-out pairs\n";
  else
    print_held_out(cam.held);
  print_light_unit(cam.light);
  const auto beside = camera_beside(out, cam.camera, reference_camera_header(cam), light_unit_why(cam));
  if (s.compact)
    save_shift_calibration(out, cam.fit.profile_rows, cam.fit.profile_cols, cam.fit.shift_rows, cam.fit.shift_cols,
                           cam.fit.calib.fixed_light);
  else
    save_calibration(out, cam.fit.calib);
  write_text_atomically(beside.path, beside.text);
  print_reference_camera(cam, out, beside.path);
  return 0;
}

// The camera's hot pixels found from the first pairs' raw frames (optics/hot_pixels.hpp), with those
// its file lists already; printed. A share of the frame too large to be stuck pixels is reported and
// not listed.
constexpr size_t kHotPixelFrames = 64, kHotPixelFramesAtLeast = 16;
// Fewer display-capture pairs than this cannot identify free factors (they need thousands).
constexpr int64_t kFewPairs = 64;
std::vector<std::array<int64_t, 2>> hot_pixels_of(const std::vector<Pair>& pairs, const CameraConfig& camera) {
  auto listed = camera.raw.hot_pixels;
  if (pairs.size() < kHotPixelFramesAtLeast) {
    std::cout << "hot pixels: not looked for (it needs " << kHotPixelFramesAtLeast << " pairs or more)\n";
    return listed;
  }
  HotPixelFinder finder({12, camera.raw.adc_bits});
  for (size_t i = 0; i < std::min(pairs.size(), kHotPixelFrames); ++i)
    finder.add(load_raw_unit(pairs[i].meas, camera.raw));
  const auto found = finder.find();
  const auto frame = static_cast<size_t>(camera.raw.raw_height * camera.raw.raw_width);
  if (found.size() > frame / 100) {
    std::cout << "hot pixels: " << found.size() << " pixels differ from their neighbours in all " << finder.frames()
              << " captures, more than 1 % of the frame: a fixed pattern (a dirty sensor, a screen in the light "
                 "path?), not stuck pixels; none listed\n";
    return listed;
  }
  listed.insert(listed.end(), found.begin(), found.end());
  std::sort(listed.begin(), listed.end());
  listed.erase(std::unique(listed.begin(), listed.end()), listed.end());
  require(static_cast<int64_t>(listed.size()) <= kMaxHotPixels, "calibrate",
          std::to_string(found.size()) + " hot pixels found and " + std::to_string(camera.raw.hot_pixels.size()) +
              " listed by the camera file make " + std::to_string(listed.size()) + ", more than the " +
              std::to_string(kMaxHotPixels) +
              " a camera file may list: too many to be stuck pixels (a broken "
              "sensor, or a camera file listing another sensor's); check the camera file's hot_pixels");
  std::cout << "hot pixels: " << found.size() << " found in " << finder.frames() << " captures (" << listed.size()
            << " listed in the camera file; each is replaced by its neighbours' mean)\n";
  return listed;
}

// A pair's scene planes {4,N,N} (b, gb, gr, r), linear light, from its photograph.
torch::Tensor scene_planes_of(const std::filesystem::path& gt, int64_t N) {
  auto rgb = read_rgb(gt);
  if (rgb.size(1) != N || rgb.size(2) != N) rgb = resize(rgb, N, N).clamp(0, 1);
  return rgb_to_bayer_planes(srgb_to_linear(rgb));
}

// The pair the calibration reads (optics/calibrate_dataset.hpp) from a raw window before centring.
CapturePair capture_pair_of(const torch::Tensor& window, const torch::Tensor& scene, const RawGeometry& g) {
  const double saturated = at_full_scale(window, g.adc_bits).to(torch::kFloat32).mean().item<double>();
  return CapturePair{without_level(double_centre(window, g.centring), g.centring), scene, window.mean({1, 2}),
                     saturated};
}

// One line when one axis's shift is borne out by the pairs and the other's is not (each axis's
// structured factor against a free one, with the other axis structured), with what to try.
void say_unfound_axis(const DatasetCalibration& fit) {
  const auto& share = fit.axis_explains;
  // An axis is found when its structured factor explains enough and its search found a minimum inside
  // the range (not at its edge).
  const bool rows = share[0] >= kStructureExplainsAtLeast && !fit.shift_at_edge[0];
  const bool cols = share[1] >= kStructureExplainsAtLeast && !fit.shift_at_edge[1];
  if (rows == cols) return;
  const char* found = rows ? "row" : "column";
  const char* lost = rows ? "column" : "row";
  const int l = rows ? 1 : 0;
  std::cerr << "calibrate: warning: the " << found << " shift (" << std::setprecision(4)
            << fit.searched_shifts[rows ? 0 : 1] << ") is found but not the " << lost << " shift (its search gave "
            << fit.searched_shifts[l]
            << (fit.shift_at_edge[l]
                    ? ", at the edge of the range searched"
                    : ", which explains " + std::to_string(share[l]) + " of what a free factor explains")
            << "): check the camera file's crop and rotation along the " << lost
            << "s, and calibrate from more pairs (all of --limit's; 500 or more)\n";
}

// The mask's rotation on the sensor (optics/rotation_estimate.hpp): the first pairs are decoded once
// and calibrated again at each angle the search tries; printed, angle by angle.
constexpr int64_t kRotationPairs = 64, kRotationPairsAtLeast = 8;
double rotation_of(const std::vector<Pair>& pairs, const CameraConfig& camera, DatasetCalibrationOptions o) {
  const auto count = std::min<int64_t>(static_cast<int64_t>(pairs.size()), kRotationPairs);
  if (count < kRotationPairsAtLeast) {
    std::cout << "rotation: not estimated (it needs " << kRotationPairsAtLeast << " pairs or more); "
              << camera.raw.rotation << " rad from the camera file\n";
    return camera.raw.rotation;
  }
  std::vector<torch::Tensor> planes, scenes;  // decoded once: {4,H/2,W/2} repaired, {4,N,N}
  for (int64_t i = 0; i < count; ++i) {
    const auto& p = pairs[static_cast<size_t>(i)];
    planes.push_back(repaired_planes(load_raw_unit(p.meas, camera.raw), camera.raw));
    scenes.push_back(scene_planes_of(p.gt, camera.scene_size));
  }
  o.progress = false;
  o.iterations = std::min(o.iterations, 4);
  // The angle is read from the structured model's residual (free factors absorb a rotation); whether
  // the camera has the structure is the main fit's verdict. A few mrad do not move the shadow's shift:
  // the first angle's searches serve the others (each fit would otherwise search four times).
  o.judge_structure = false;
  auto geometry = camera.raw;
  torch::Tensor valid;  // the window's pixels read from inside the planes at the angle tried
  const auto window_pair = [&](int64_t i) {
    return WindowPair{rotated_window(planes[static_cast<size_t>(i)], geometry), scenes[static_cast<size_t>(i)], valid};
  };
  const auto project = [&](double angle) {
    geometry.rotation = angle;
    valid = window_inside_plane(planes[0].size(1), planes[0].size(2), geometry);
    const auto fit = calibrate_from_pairs(
        count,
        [&](int64_t i) {
          const auto w = window_pair(i);
          return capture_pair_of(w.window, w.scene, geometry);
        },
        geometry.crop[2], geometry.crop[3], camera.scene_size, o);
    const double d = rotation_residual_projection(count, window_pair, fit, {geometry.crop[0], geometry.crop[1]});
    if (o.shifts[0] == 0) o.shifts = fit.searched_shifts;
    std::cout << "rotation: at " << std::setprecision(5) << angle << " rad the residual holds " << std::setprecision(3)
              << d << " rad of rotation\n"
              << std::flush;
    return d;
  };
  RotationSearchOptions so;
  so.start = camera.raw.rotation;
  const auto search = search_rotation(project, so);
  std::cout << "rotation: " << std::setprecision(5) << search.angle << " rad (the mask's rotation on the sensor, from "
            << count << " pairs; written to the camera file"
            << (!search.slope_found
                    ? "; the residual showed no slope to follow: the angle tried whose residual holds the least"
                : search.converged ? ""
                                   : "; not settled within the fits allowed")
            << ")\n";
  return search.angle;
}

// `flatnet calibrate --dataset DIR`: the calibration identified from display-capture pairs
// (optics/calibrate_dataset.hpp), written with a camera.yaml beside it and the fit per channel.
// The display-capture pairs `calibrate --dataset` (or --meas-list/--gt-list) names, the first
// --limit of them.
std::vector<Pair> dataset_pairs(const cxxopts::ParseResult& r, const CalibrateSettings& s) {
  std::vector<Pair> pairs;
  if (r.count("meas-list") || r.count("gt-list")) {  // FlatNet's own list files
    require(r.count("meas-list") && r.count("gt-list"), "--meas-list", "give both --meas-list and --gt-list");
    DatasetLists lists{s.meas_list, s.gt_list, {}};
    if (r.count("root")) lists.root = s.root;
    pairs = read_pairs(lists);
  } else {
    const std::filesystem::path dir = s.dataset;
    for (const auto& split : {"train", "val"}) {
      const auto lists = split_lists(dir, split);
      if (!std::filesystem::exists(lists.meas_list)) continue;
      const auto part = read_pairs(lists);
      pairs.insert(pairs.end(), part.begin(), part.end());
      if (s.split == split) break;
    }
    require(!pairs.empty(), dir,
            "holds no train_meas.txt / val_meas.txt lists (FlatNet's layout); or give --meas-list and --gt-list");
  }
  const auto limit = s.limit;
  require(limit >= 0, "--limit", "0 (all) or more");
  if (limit > 0 && static_cast<int64_t>(pairs.size()) > limit) pairs.resize(static_cast<size_t>(limit));
  return pairs;
}

DatasetCalibrationOptions dataset_calibration_options(const CalibrateSettings& s) {
  DatasetCalibrationOptions o;
  o.iterations = s.iterations;
  o.seed = s.seed;
  o.cache_bytes = static_cast<int64_t>(s.cache_mb * (1 << 20));
  require(o.iterations >= 1 && o.cache_bytes >= 0, "calibrate", "--iterations >= 1 and --cache-mb >= 0");
  const auto structure = s.structure;
  require(structure == "shift" || structure == "free", "calibrate",
          "--structure is shift (a FlatCam's shadow moves with the scene) or free, not '" + structure + "'");
  o.structure = structure == "shift" ? FactorStructure::Shift : FactorStructure::Free;
  // The shift structure is fitted after the free passes and judged once each axis has searched its
  // shift twice: fewer steps would keep a structure nothing judged.
  const int judged_at = o.free_passes + 2;
  require(o.structure == FactorStructure::Free || o.iterations >= judged_at, "--iterations",
          std::to_string(o.iterations) + " steps end before the shift structure is judged (" +
              std::to_string(o.free_passes) + " free steps, then two shift searches per axis): at least " +
              std::to_string(judged_at) + " with --structure shift, or give --structure free");
  const auto colour_mix = s.colour_mix;
  require(colour_mix == "identify" || colour_mix == "none", "--colour-mix",
          "identify (fit each plane's shares of the primaries) or none, not '" + colour_mix + "'");
  o.identify_mix = colour_mix == "identify";
  return o;
}

// The calibration, its camera file and what the fit found, printed.
void write_dataset_calibration(const DatasetCalibration& fit, const CameraConfig& camera,
                               const DatasetCalibrationOptions& o, size_t pair_count,
                               const std::optional<Calibration>& truth, const std::filesystem::path& out) {
  auto known = camera;
  known.noise_gain = fit.noise_gain;
  known.noise_floor = fit.noise_floor;
  known.dark = fit.dark;
  known.fit_threshold = fit.fit_threshold;
  known.leak_threshold = fit.leak_threshold;
  known.colour_mix = fit.colour_mix.defined() ? colour_mix_rows(fit.colour_mix) : decltype(known.colour_mix){};
  std::ostringstream fit_text;
  fit_text << "# identified by `flatnet calibrate --dataset` from " << fit.pairs << " display-capture pairs, "
           << fit.iterations << " alternating steps; relative fit residual per channel (b, gb, gr, r):";
  for (const double v : fit.residual) fit_text << " " << std::setprecision(4) << v;
  if (o.structure == FactorStructure::Shift && !fit.structure_rejected)
    fit_text << "\n# the shadow moves " << std::setprecision(6) << fit.shift_rows << " sensor pixels per scene row, "
             << fit.shift_cols << " per scene column";
  fit_text << "\n";
  const auto beside = camera_beside(out, known, fit_text.str(), "");
  save_calibration(out, fit.calib);
  write_text_atomically(beside.path, beside.text);
  const auto& yaml_path = beside.path;
  std::cout << "wrote " << out.string() << " and " << yaml_path.string() << " from " << fit.pairs << " pairs ("
            << fit.iterations << " steps)\nfit residual ||Y - P X Q^T - s a b^T|| / ||Y||:";
  for (int c = 0; c < 4; ++c) std::cout << " " << kChannelNames[c] << " " << std::setprecision(4) << fit.residual[c];
  std::cout << "\nsensor noise: variance " << fit.noise_gain << " x (level - " << fit.dark << ") + " << fit.noise_floor
            << " (full well about " << (fit.noise_gain > 0 ? 1 / fit.noise_gain : 0)
            << " electrons)\ncamera fit: its own pairs"
            << " fit up to the threshold " << fit.fit_threshold;
  if (fit.leak_threshold > 0) std::cout << " and leak up to " << fit.leak_threshold;
  std::cout << ", written to the camera file (this calibration's error is part of what it leaves outside its span)\n";
  if (!known.colour_mix.empty()) {
    std::cout << "colour mix (each plane's shares of the display's R, G, B; written to the camera file, undone by "
                 "Tikhonov and TV):";
    for (int p = 0; p < 4; ++p)
      std::cout << " " << kChannelNames[p] << " " << std::setprecision(3) << known.colour_mix[p][0] << "/"
                << known.colour_mix[p][1] << "/" << known.colour_mix[p][2];
    std::cout << "\n";
  }
  if (fit.structure_rejected) {
    if (fit.shift_at_edge[0] || fit.shift_at_edge[1])
      std::cout << "shift structure rejected: the shift search ended at the edge of its range (" << o.shift.min_shift
                << " to " << o.shift.max_shift << " sensor pixels per scene pixel, both ways) on "
                << (fit.shift_at_edge[0] && fit.shift_at_edge[1] ? "both axes"
                    : fit.shift_at_edge[0]                       ? "the rows"
                                                                 : "the columns")
                << " (searched " << std::setprecision(4) << fit.searched_shifts[0] << " row, " << fit.searched_shifts[1]
                << " column): no shift inside it explains the pairs; free factors were fitted, which need thousands "
                   "of pairs\n";
    else
      std::cout << "shift structure rejected: it explains " << std::setprecision(3) << fit.structure_explains
                << " of what free factors explain (a mask that is not one moving shadow?); free factors were fitted, "
                   "which need thousands of pairs\n";
    // A handful of pairs whose shadow no shift explains are, most often, direct captures and someone's
    // reconstructions of them (FlatNet's fc_*.png and rec_*.png), not display captures of photographs.
    if (static_cast<int64_t>(pair_count) < kFewPairs)
      std::cerr << "calibrate: warning: " << pair_count
                << " pairs whose shadow no shift explains look like captures and reconstructions of them, not "
                   "display captures of photographs; for those, run `flatnet calibrate --references` (same lists); "
                   "free factors from so few pairs do not describe the camera\n";
  } else if (o.structure == FactorStructure::Shift) {
    std::cout << "shift structure: the shadow moves " << std::setprecision(6) << fit.shift_rows
              << " sensor pixels per scene row, " << fit.shift_cols << " per scene column; it explains "
              << std::setprecision(3) << fit.structure_explains << " of what free factors explain\n";
    if (static_cast<int64_t>(pair_count) < kFewPairs)
      std::cerr << "calibrate: warning: a shift structure from " << pair_count << " pairs (under " << kFewPairs
                << ") is uncertain; if these are captures and someone's reconstructions of them rather than display "
                   "captures of photographs, run `flatnet calibrate --references` (same lists)\n";
  }
  if (o.structure == FactorStructure::Shift) say_unfound_axis(fit);
  if (truth) {  // a simulated camera: how close to its true response
    const auto err = calibration_error(fit.calib, *truth);
    std::cout << "relative error against the rig's true response: P " << 100 * err.p << " %, Q " << 100 * err.q
              << " %, forward model " << 100 * err.forward << " %\n";
  }
}

int calibrate_from_dataset(const cxxopts::ParseResult& r, const CalibrateSettings& s) {
  auto camera = camera_from(r);
  const std::filesystem::path out = s.out;
  require(out.extension() == ".mat", "--out",
          "the calibration is a .mat file (FlatNet's layout), got '" + out.string() + "'");
  // Every file this command reads is an input that no output may land on, even with --force: the
  // camera file given, the rig and calibration it names, and the lists.
  std::vector<std::filesystem::path> inputs = {camera.rig, camera.calibration};
  if (r.count("camera")) inputs.push_back(s.camera);
  for (const auto* flag : {"meas-list", "gt-list", "white-capture"})
    if (r.count(flag)) inputs.push_back(r[flag].as<std::string>());
  require(!r.count("white-capture") || s.references, "--white-capture",
          "sets the light unit of a calibration from references (--references); a display-capture calibration "
          "is in the display's light already");
  require(!(r.count("scene-light") && r.count("white-capture")), "--scene-light",
          "is the light unit's prior without a white capture; --white-capture measures it (give one)");
  const bool force = s.force;
  auto pairs = dataset_pairs(r, s);
  require(!pairs.empty(), "calibrate", "the lists name no pairs");
  // The captures' size against the geometry from the first one's header, before anything the
  // geometry's size sets is allocated (the rest are checked as each is read).
  check_raw_header(pairs.front().meas, camera.raw);
  // A simulated camera's truth, for the error printed at the end: read now, so that a missing rig
  // is named before the fit runs.
  std::optional<Calibration> truth;
  if (!camera.rig.empty()) truth = ideal_calibration(load_camera_rig(camera), camera.raw);
  // The pairs' files are inputs too (a reference .mat, a capture): no output lands on one, even with
  // --force. The camera.yaml written beside the calibration is an output too: an existing one (perhaps
  // hand-tuned) is replaced only with --force, and never when it is one of the inputs.
  for (const auto& p : pairs) inputs.insert(inputs.end(), {p.meas, p.gt});
  require_new_output(out, force, inputs);
  require_new_output(out.parent_path() / "camera.yaml", force, inputs);
  if (s.references) return calibrate_from_reference_pairs(r, s, camera, pairs, out);
  camera.raw.hot_pixels = hot_pixels_of(pairs, camera);
  const auto N = camera.scene_size;
  auto load = [&](int64_t i) {
    const auto& p = pairs[static_cast<size_t>(i)];
    const auto window = raw_window(load_raw_unit(p.meas, camera.raw), camera.raw);  // {4,rows,cols}
    return capture_pair_of(window, scene_planes_of(p.gt, N), camera.raw);
  };
  const auto o = dataset_calibration_options(s);
  const auto rotation = s.rotation;
  require(rotation == "estimate" || rotation == "keep", "--rotation",
          "estimate (search the mask's rotation on the sensor) or keep (the camera file's), not '" + rotation + "'");
  // The rotation search fits the shift structure at each angle: free factors absorb a rotation instead.
  require(!(rotation == "estimate" && o.structure == FactorStructure::Free && r.count("rotation")), "--rotation",
          "estimate needs --structure shift (free factors absorb a rotation and cannot measure it); give "
          "--rotation keep, or state the angle in the camera file");
  if (rotation == "estimate" && o.structure == FactorStructure::Shift)
    camera.raw.rotation = rotation_of(pairs, camera, o);
  else if (o.structure == FactorStructure::Free)
    std::cout << "rotation: " << camera.raw.rotation
              << " rad from the camera file (not searched: free factors absorb a rotation)\n";
  std::cerr << "calibrate: " << pairs.size() << " display-capture pairs, " << camera.raw.crop[2] << "x"
            << camera.raw.crop[3] << " planes, " << N << "x" << N << " scenes\n";
  const auto fit =
      calibrate_from_pairs(static_cast<int64_t>(pairs.size()), load, camera.raw.crop[2], camera.raw.crop[3], N, o);
  write_dataset_calibration(fit, camera, o, pairs.size(), truth, out);
  return 0;
}

using CS = CalibrateSettings;

const FlagTable<CS>& calibrate_file_flags() {
  static const FlagTable<CS> rows = {
      {"rig", &CS::rig, "simulate the captures with this rig (.mat) or camera (.yaml)"},
      {"captures", &CS::captures, "folder of real captures, one PNG per pattern name"},
      {"write-patterns", &CS::write_patterns, "write the pattern images for display into this folder and stop"},
      {"camera", &CS::camera, "camera .yaml for --captures (geometry, preprocessing)"},
      {"out", &CS::out, "calibration .mat to write (FlatNet layout)"},
      {"force", &CS::force, "replace an existing --out file"},
  };
  return rows;
}

const FlagTable<CS>& calibrate_pair_files() {
  static const FlagTable<CS> rows = {
      {"dataset", &CS::dataset, "dataset folder in FlatNet's layout (train_meas.txt, train_gt.txt, ...)"},
      {"meas-list", &CS::meas_list, "FlatNet's own capture list (with --gt-list)"},
      {"gt-list", &CS::gt_list, "FlatNet's own photograph list"},
      {"root", &CS::root, "folder the lists' lines are relative to (default: the lists' folder)"},
  };
  return rows;
}

// --references and the files of a calibration from references (its numbers: calibrate_reference_flags).
const FlagTable<CS>& calibrate_reference_inputs() {
  static const FlagTable<CS> rows = {
      {"references", &CS::references,
       "the photographs are someone else's reconstructions of the captures (a lost calibration): a gain and "
       "offset per pair and channel, pixels clipped at zero left out, judged by leave-one-out"},
      {"white-capture", &CS::white_capture,
       "a raw capture of a uniform white scene (the display's white filling the view), taken as the captures "
       "were: sets the calibration's light unit, so pictures show the scene's light, not the references' stretch"},
      {"compact", &CS::compact,
       "write the calibration as its profiles and shifts (kilobytes; flatnet expands it) instead of FlatNet's "
       "P1b..Q1r matrices"},
  };
  return rows;
}

const FlagTable<CS>& calibrate_pattern_flags() {
  static const FlagTable<CS> rows = {
      {"average", &CS::average, "frames averaged per pattern (simulated)", 1, 100000, "at least 1 frame"},
      {"noise", &CS::noise, "on|off (simulated)"},
      {"seed", &CS::seed, "noise seed (simulated); the random starts of a fit from pairs"},
      {"level", &CS::level, "display code (sRGB) of the patterns' bright parts", 1, 255, "1 to 255"},
  };
  return rows;
}

const FlagTable<CS>& calibrate_dataset_flags() {
  static const FlagTable<CS> rows = {
      {"split", &CS::split, "train (the train list only) or all (train and val)"},
      {"limit", &CS::limit, "use the first N pairs (0: all)", 0, 1e12, "0 (all) or more"},
      {"iterations", &CS::iterations, "alternating least-squares steps at most", 1, 1e6, "at least 1"},
      {"structure", &CS::structure,
       "shift: each factor's columns are one profile moved by a shift found from the data (a FlatCam's "
       "shadow; few pairs suffice); free: every entry free (any separable camera; needs many pairs)"},
      {"colour-mix", &CS::colour_mix,
       "identify: each Bayer plane's shares of the display's three primaries are fitted with the factors and "
       "written to the camera file (cross-talk); none: b sees blue alone, gb and gr green, r red"},
      {"rotation", &CS::rotation,
       "estimate: the mask's rotation on the sensor is searched (a calibration of the first pairs per angle "
       "tried) and written to the camera file; keep: the camera file's rotation"},
      {"cache-mb", &CS::cache_mb, "decoded pairs kept in memory (the rest are re-read each pass)", 0, 1e9,
       "0 or more megabytes"},
  };
  return rows;
}

const FlagTable<CS>& calibrate_reference_flags() {
  static const FlagTable<CS> rows = {
      {"reference-order", &CS::reference_order, "colour order of the reference files: rgb or bgr"},
      {"reference-lambda", &CS::reference_lambda,
       "Tikhonov regulariser of the held-out check and the camera file, relative to the largest squared "
       "singular value product"},
      {"fixed-light", &CS::fixed_light,
       "on: a light every capture holds whatever the scene (flare, stray light) is fitted as its own term, "
       "written with the calibration and subtracted before inversion; off: the captures hold the scene's light "
       "alone"},
      {"shared-mask", &CS::shared_mask,
       "on: the four Bayer planes' profiles fitted as one mask per axis, each plane seeing it through a short "
       "kernel of its own (its sub-pixel offset, blur and gain); off: a profile per plane"},
      {"mask-taps", &CS::mask_taps,
       "with --shared-mask on: samples in each plane's kernel (odd, 3 to 15; 3 holds a sub-pixel offset and a "
       "little blur)"},
      {"min-shift", &CS::min_shift, "smallest |shadow shift| searched, sensor pixels per scene pixel"},
      {"max-shift", &CS::max_shift, "largest |shadow shift| searched"},
      {"white-light", &CS::white_light, "the white capture's light relative to the display's white"},
      {"scene-light", &CS::scene_light,
       "without --white-capture: the mean light the pairs' scenes are taken to hold, relative to the display's "
       "white (the light unit is not in the data; the default is a typical training photograph at 0.29 of the "
       "display's light); 0: the references' own units",
       0, 1e3, "0 (the references' units) to 1000"},
  };
  return rows;
}

}  // namespace

CommandFlags calibrate_command_flags() {
  return command_flags("calibrate", calibrate_file_flags(), calibrate_pattern_flags(), calibrate_pair_files(),
                       calibrate_dataset_flags(), calibrate_reference_inputs(), calibrate_reference_flags());
}

// Every flag of `flatnet calibrate`, by group.
cxxopts::Options calibrate_options() {
  cxxopts::Options o("flatnet calibrate",
                     "FlatCam calibration (Asif et al. 2017) from separable Hadamard pattern captures.\n"
                     "  simulated:  flatnet calibrate --rig RIG.mat|CAMERA.yaml --out calib.mat\n"
                     "  real:       flatnet calibrate --write-patterns DIR   (show each, capture it as DIR2/NAME.png)\n"
                     "              flatnet calibrate --captures DIR2 --camera CAMERA.yaml --out calib.mat\n"
                     "  from data:  flatnet calibrate --dataset DIR --camera GEOMETRY.yaml --out calib.mat\n"
                     "              (display-capture pairs in FlatNet's layout, or --meas-list/--gt-list [--root])");
  add_flags(o, calibrate_file_flags());
  add_flags(o, calibrate_pattern_flags());
  const std::string pairs_group = "from display-capture pairs";
  add_flags(o, calibrate_pair_files(), pairs_group);
  add_flags(o, calibrate_dataset_flags(), pairs_group);
  const std::string references_group = "from a few captures and reconstructions of them (with --meas-list/--gt-list)";
  add_flags(o, calibrate_reference_inputs(), references_group);
  add_flags(o, calibrate_reference_flags(), references_group);
  add_common(o);
  return o;
}

// The flags of a calibration from references do nothing in any other: given there, they are refused
// (a flag that changes nothing without a word is a silent wrong answer). --white-light likewise needs
// the white capture whose light it states.
void require_reference_flags_used(const cxxopts::ParseResult& r) {
  require(!r.count("white-light") || r.count("white-capture"), "--white-light",
          "is the light of the white capture (--white-capture); without one it does nothing (--scene-light sets the "
          "light unit's prior instead)");
  if (r.count("references")) return;
  // --white-capture keeps its own message (calibrate_from_dataset): it names what a display capture is.
  std::vector<std::string> flags = {"compact"};
  for (const auto& row : calibrate_reference_flags()) flags.emplace_back(row.flag);
  for (const auto& flag : flags)
    require(!r.count(flag), "--" + flag,
            "belongs to a calibration from a few captures and reconstructions of them (--references); this "
            "calibration does not read it");
}

int calibrate(int argc, char** argv) {
  auto o = calibrate_options();
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  CalibrateSettings s;
  for (const auto* table : {&calibrate_file_flags(), &calibrate_pattern_flags(), &calibrate_pair_files(),
                            &calibrate_dataset_flags(), &calibrate_reference_inputs(), &calibrate_reference_flags()})
    read_flags(r, *table, s);
  const int level = s.level;

  if (r.count("write-patterns")) {
    const auto camera = camera_from(r);
    const std::filesystem::path dir = s.write_patterns;
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
  require(s.split == "train" || s.split == "all", "--split", "expected train or all");
  require_reference_flags_used(r);
  if (r.count("dataset") || r.count("meas-list")) return calibrate_from_dataset(r, s);
  const std::filesystem::path out = s.out;
  std::vector<std::filesystem::path> inputs;
  for (const auto* flag : {"rig", "camera"})
    if (r.count(flag)) inputs.push_back(r[flag].as<std::string>());
  std::optional<CameraConfig> rig_camera;
  if (r.count("rig")) {
    rig_camera = load_camera_config(s.rig);
    inputs.insert(inputs.end(), {rig_camera->rig, rig_camera->calibration});
  }
  require_new_output(out, s.force, inputs);

  Calibration est;
  std::optional<Calibration> truth;
  if (rig_camera) {
    const auto& camera = *rig_camera;
    require(!camera.rig.empty(), s.rig, "names no rig to simulate with");
    const auto rig = load_camera_rig(camera);
    const bool noise = s.noise == "on";
    const int average = std::max(1, s.average);
    auto capture = rig_pattern_capture(rig, camera.raw, level, noise, average, at::detail::createCPUGenerator(s.seed));
    est = estimate_calibration(camera.scene_size, capture, level);
    truth = ideal_calibration(rig, camera.raw);
  } else {
    const auto camera = camera_from(r);
    const std::filesystem::path dir = s.captures;
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
