#include "io/camera_config.hpp"

#include <algorithm>
#include <cmath>
#include <cstdlib>

#include "io/image.hpp"
#include "io/yaml_text.hpp"

#include <yaml-cpp/yaml.h>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/mat.hpp"

namespace flatnet {

std::string centring_name(Centring c) {
  switch (c) {
    case Centring::plane:
      return "plane";
    case Centring::flatnet:
      return "flatnet";
    case Centring::level:
      return "level";
    case Centring::none:
      break;
  }
  return "none";
}

Centring parse_centring(const std::string& s, const std::filesystem::path& where) {
  if (s == "plane") return Centring::plane;
  if (s == "flatnet") return Centring::flatnet;
  if (s == "none") return Centring::none;
  if (s == "level") return Centring::level;
  throw Error(where, "centring must be plane, level, flatnet or none, got '" + s + "'");
}

std::filesystem::path default_camera_path() { return data_dir() / "configs" / "cameras" / "sim.yaml"; }

namespace {

const std::vector<std::string> kKnownKeys = {
    "name",       "raw_height",  "raw_width",   "adc_bits",      "rotation",        "crop",
    "centring",   "scene_size",  "calibration", "rig",           "tikhonov_lambda", "tv_lambda",
    "noise_gain", "noise_floor", "dark",        "fit_threshold", "leak_threshold",  "open_light",
    "bench",      "hot_pixels",  "colour_mix",  "display_gamma"};

void validate(const CameraConfig& c, const std::filesystem::path& path) {
  const auto& g = c.raw;
  require(g.raw_height > 0 && g.raw_width > 0 && g.raw_height % 2 == 0 && g.raw_width % 2 == 0, path,
          "raw_height and raw_width must be positive and even (Bayer mosaic)");
  require(g.adc_bits >= 1 && g.adc_bits <= 16, path, "adc_bits must be within 1..16");
  require(g.crop[0] >= 0 && g.crop[1] >= 0 && g.crop[2] > 0 && g.crop[3] > 0 &&
              g.crop[0] + g.crop[2] <= g.plane_height() && g.crop[1] + g.crop[3] <= g.plane_width(),
          path,
          "crop [top, left, height, width] must lie inside the " + std::to_string(g.plane_height()) + "x" +
              std::to_string(g.plane_width()) + " Bayer plane");
  require(g.raw_height <= 65536 && g.raw_width <= 65536, path, "raw_height and raw_width must be at most 65536");
  require(std::isfinite(g.rotation) && std::abs(g.rotation) <= kMaxCameraRotation, path,
          "rotation is in radians, within [-" + std::to_string(kMaxCameraRotation) + ", " +
              std::to_string(kMaxCameraRotation) + "] (about 10 degrees); got " + std::to_string(g.rotation));
  require(static_cast<int64_t>(g.hot_pixels.size()) <= kMaxHotPixels, path,
          "hot_pixels lists " + std::to_string(g.hot_pixels.size()) + " pixels; at most " +
              std::to_string(kMaxHotPixels) + " (a sensor with more is broken, not calibrated)");
  for (const auto& [row, col] : g.hot_pixels)
    require(row >= 0 && row < g.raw_height && col >= 0 && col < g.raw_width, path,
            "hot_pixels: [" + std::to_string(row) + ", " + std::to_string(col) + "] lies outside the " +
                std::to_string(g.raw_height) + "x" + std::to_string(g.raw_width) + " raw frame (rows x columns)");
  if (!c.colour_mix.empty()) {
    require(c.colour_mix.size() == 4, path, "colour_mix: 4 rows (b, gb, gr, r) of 3 shares (R, G, B)");
    for (const auto& row : c.colour_mix)
      for (const double v : row)
        require(std::isfinite(v) && std::abs(v) <= 10, path,
                "colour_mix: each share is a finite number within [-10, 10]");
    constexpr double kColourMixSumTolerance = 0.02;
    constexpr const char* kPlaneNames[] = {"b", "gb", "gr", "r"};
    // Each row is a plane's shares of the primaries, scaled to sum 1 (calibrate --dataset writes it so):
    // a row summing to 2 would brighten that plane's scene twice over, silently.
    for (size_t p = 0; p < c.colour_mix.size(); ++p) {
      const auto& row = c.colour_mix[p];
      const double sum = row[0] + row[1] + row[2];
      require(std::abs(sum - 1) <= kColourMixSumTolerance, path,
              "colour_mix: row " + std::to_string(p + 1) + " (" + std::string(kPlaneNames[p]) + ") sums to " +
                  std::to_string(sum) + "; each plane's shares of the primaries sum to 1 (within " +
                  std::to_string(kColourMixSumTolerance) +
                  "): scale the row, or put the plane's gain in the calibration");
    }
    // The primaries must be recoverable from the planes: the mix has rank 3, not barely.
    const auto smallest = torch::linalg_svdvals(colour_mix_matrix(c.colour_mix)).min().item<double>();
    require(smallest > 1e-3, path,
            "colour_mix cannot be undone (its smallest singular value is " + std::to_string(smallest) +
                "): two primaries look alike to every plane");
  }
  require(c.scene_size > 0 && c.scene_size <= 4096, path, "scene_size must lie within 1..4096");
  require(std::isfinite(c.noise_gain) && std::isfinite(c.noise_floor) && std::isfinite(c.dark) && c.noise_gain >= 0 &&
              c.noise_gain < 1 && c.noise_floor >= 0 && c.noise_floor < 1 && c.dark >= 0 && c.dark < 1,
          path, "noise_gain, noise_floor and dark are full-scale quantities within [0, 1)");
  require(std::isfinite(c.fit_threshold) && (c.fit_threshold == 0 || (c.fit_threshold >= 1 && c.fit_threshold <= 1e3)),
          path, "fit_threshold is 0 (the camera fit's own) or a ratio within [1, 1000]");
  require(
      std::isfinite(c.leak_threshold) && (c.leak_threshold == 0 || (c.leak_threshold >= 1 && c.leak_threshold <= 1e3)),
      path, "leak_threshold is 0 (the camera fit's own) or a ratio within [1, 1000]");
  require(std::isfinite(c.display_gamma) && (c.display_gamma == 0 || (c.display_gamma >= kLeastDisplayGamma &&
                                                                      c.display_gamma <= kLargestDisplayGamma)),
          path, "display_gamma is 0 (the sRGB curve) or a power within [0.5, 3]");
  require(std::isfinite(c.open_light) && c.open_light >= 0 && c.open_light <= 1e3, path,
          "open_light is 0 (unknown) or a plane's level per unit of mean scene light, within (0, 1000]");
  // Above ~1e4 the SVD filter s / (s^2 + lambda) is ~0 for any real camera: black images, not an answer.
  require(std::isfinite(c.tikhonov_lambda) && std::isfinite(c.tv_lambda) && c.tikhonov_lambda > 0 && c.tv_lambda > 0 &&
              c.tikhonov_lambda <= 1e4 && c.tv_lambda <= 1e4,
          path, "regularisation weights (tikhonov_lambda, tv_lambda) must lie in (0, 1e4]");
}

}  // namespace

CameraConfig camera_from_node(const YAML::Node& y, const std::filesystem::path& path,
                              const std::filesystem::path& base);

CameraConfig load_camera_config(const std::filesystem::path& path) {
  require(std::filesystem::exists(path), path, "no such camera file");
  CameraConfig c;
  if (path.extension() == ".mat") {
    MatReader rig(path);
    c.name = path.stem().string();
    c.rig = path;
    const auto crop = rig.read("crop", {4});
    for (int i = 0; i < 4; ++i) c.raw.crop[i] = static_cast<int64_t>(crop[i].item<double>());
    c.raw.adc_bits = static_cast<int>(rig.read_scalar("adc_bits"));
    validate(c, path);
    return c;
  }
  return camera_from_node(load_yaml_file(path), path, path.parent_path());
}

CameraConfig camera_from_yaml_text(const std::string& text, const std::filesystem::path& where) {
  return camera_from_node(parse_yaml_document(text, where), where, {});
}

std::string camera_file_text(const CameraConfig& camera, const std::string& calibration_name,
                             const std::string& comment, const std::filesystem::path& where) {
  auto known = camera;
  known.rig.clear();
  validate(known, where);  // values YAML cannot carry back (inf, nan) are named here, not as a parse error
  const auto text = comment + camera_geometry_yaml(known) + "calibration: " + yaml_quoted(calibration_name) + "\n";
  camera_from_yaml_text(text, where);
  return text;
}

std::string camera_geometry_yaml(const CameraConfig& c) {
  const auto& g = c.raw;
  std::ostringstream os;
  os << "name: " << yaml_quoted(c.name) << "\n"
     << "raw_height: " << g.raw_height << "\nraw_width: " << g.raw_width << "\n"
     << "adc_bits: " << g.adc_bits << "\n";
  os.precision(17);
  os << "rotation: " << g.rotation << "\n"
     << "crop: [" << g.crop[0] << ", " << g.crop[1] << ", " << g.crop[2] << ", " << g.crop[3] << "]\n"
     << "centring: " << centring_name(g.centring) << "\n";
  if (!g.hot_pixels.empty()) {
    os << "hot_pixels: [";
    for (size_t i = 0; i < g.hot_pixels.size(); ++i)
      os << (i ? ", " : "") << "[" << g.hot_pixels[i][0] << ", " << g.hot_pixels[i][1] << "]";
    os << "]\n";
  }
  os << "scene_size: " << c.scene_size << "\n"
     << "tikhonov_lambda: " << c.tikhonov_lambda << "\ntv_lambda: " << c.tv_lambda << "\n";
  if (c.knows_noise())
    os << "noise_gain: " << c.noise_gain << "\nnoise_floor: " << c.noise_floor << "\ndark: " << c.dark << "\n";
  if (c.fit_threshold > 0) os << "fit_threshold: " << c.fit_threshold << "\n";
  if (c.leak_threshold > 0) os << "leak_threshold: " << c.leak_threshold << "\n";
  if (c.open_light > 0) os << "open_light: " << c.open_light << "\n";
  if (c.display_gamma > 0) os << "display_gamma: " << c.display_gamma << "\n";
  if (!c.colour_mix.empty()) {
    os << "colour_mix: [";
    for (size_t p = 0; p < c.colour_mix.size(); ++p)
      os << (p ? ", " : "") << "[" << c.colour_mix[p][0] << ", " << c.colour_mix[p][1] << ", " << c.colour_mix[p][2]
         << "]";
    os << "]\n";
  }
  return os.str();
}

// The bench: section: each key a number within its range (a simulated bench's plausible errors),
// checked by the rule every config number is (core/util.hpp number_problem).
static BenchErrors bench_from_node(const YAML::Node& y, const std::filesystem::path& path) {
  require(y.IsMap(), path, "bench: expected a mapping of bench errors");
  BenchErrors b;
  double hot = 0;
  const std::pair<NumberRule, double*> rows[] = {
      {{"crosstalk", 0, 0.5, "a share, 0 to 0.5"}, &b.crosstalk},
      {{"mask_rotation", -0.1, 0.1, "radians, -0.1 to 0.1"}, &b.mask_rotation},
      {{"second_term", 0, 0.5, "a share, 0 to 0.5"}, &b.second_term},
      {{"flicker", 0, 0.5, "0 to 0.5"}, &b.flicker},
      {{"stray_light", 0, 0.5, "full scale, 0 to 0.5"}, &b.stray_light},
      {{"hot_pixels", 0, 1e5, "0 to 100000 pixels"}, &hot},
      {{"display_shift", -16, 16, "scene pixels, -16 to 16"}, &b.display_shift},
      {{"display_scale", 0.8, 1.25, "0.8 to 1.25"}, &b.display_scale},
      {{"calibration_error", 0, 0.5, "a share of the coded light, 0 to 0.5"}, &b.calibration_error}};
  for (const auto& kv : y) {
    const auto key = kv.first.as<std::string>(), text = kv.second.as<std::string>();
    const auto row = std::find_if(std::begin(rows), std::end(rows), [&](const auto& r) { return key == r.first.name; });
    require(row != std::end(rows), path, "unknown bench error 'bench." + printable(key) + "'");
    const auto problem = number_problem(text, row->first);
    require(problem.empty(), path,
            "bench." + key + " = " + printable(text) + " " + problem + ": " + row->first.meaning);
    *row->second = std::strtod(text.c_str(), nullptr);
  }
  b.hot_pixels = static_cast<int64_t>(hot);
  return b;
}

CameraConfig camera_from_node(const YAML::Node& y, const std::filesystem::path& path,
                              const std::filesystem::path& base) {
  CameraConfig c;
  require(y.IsMap(), path, "expected a mapping of camera settings");
  try {
    for (const auto& kv : y) {
      const auto key = kv.first.as<std::string>();
      require(std::find(kKnownKeys.begin(), kKnownKeys.end(), key) != kKnownKeys.end(), path,
              "unknown camera setting '" + key + "'");
    }
    if (y["name"]) c.name = y["name"].as<std::string>();
    if (y["raw_height"]) c.raw.raw_height = y["raw_height"].as<int64_t>();
    if (y["raw_width"]) c.raw.raw_width = y["raw_width"].as<int64_t>();
    if (y["adc_bits"]) c.raw.adc_bits = y["adc_bits"].as<int>();
    if (y["rotation"]) c.raw.rotation = y["rotation"].as<double>();
    if (y["crop"]) {
      auto v = y["crop"].as<std::vector<int64_t>>();
      require(v.size() == 4, path, "crop must be [top, left, height, width]");
      std::copy(v.begin(), v.end(), c.raw.crop.begin());
    }
    if (y["hot_pixels"]) {
      const auto list = y["hot_pixels"];
      require(list.IsSequence(), path, "hot_pixels: expected a list of [row, col] pairs");
      for (const auto& item : list) {
        require(item.IsSequence() && item.size() == 2, path, "hot_pixels: each entry is [row, col] of the raw frame");
        c.raw.hot_pixels.push_back({item[0].as<int64_t>(), item[1].as<int64_t>()});
      }
    }
    if (y["centring"]) c.raw.centring = parse_centring(y["centring"].as<std::string>(), path);
    if (y["scene_size"]) c.scene_size = y["scene_size"].as<int64_t>();
    if (y["calibration"]) c.calibration = base / y["calibration"].as<std::string>();
    if (y["rig"]) c.rig = base / y["rig"].as<std::string>();
    if (y["tikhonov_lambda"]) c.tikhonov_lambda = y["tikhonov_lambda"].as<double>();
    if (y["tv_lambda"]) c.tv_lambda = y["tv_lambda"].as<double>();
    if (y["noise_gain"]) c.noise_gain = y["noise_gain"].as<double>();
    if (y["noise_floor"]) c.noise_floor = y["noise_floor"].as<double>();
    if (y["dark"]) c.dark = y["dark"].as<double>();
    if (y["fit_threshold"]) c.fit_threshold = y["fit_threshold"].as<double>();
    if (y["leak_threshold"]) c.leak_threshold = y["leak_threshold"].as<double>();
    if (y["open_light"]) c.open_light = y["open_light"].as<double>();
    if (y["display_gamma"]) c.display_gamma = y["display_gamma"].as<double>();
    if (y["bench"]) c.bench = bench_from_node(y["bench"], path);
    if (y["colour_mix"]) {
      const auto rows = y["colour_mix"];
      require(rows.IsSequence() && rows.size() == 4, path, "colour_mix: 4 rows (b, gb, gr, r) of 3 shares (R, G, B)");
      for (const auto& row : rows) {
        require(row.IsSequence() && row.size() == 3, path, "colour_mix: each row is 3 shares (R, G, B)");
        c.colour_mix.push_back({row[0].as<double>(), row[1].as<double>(), row[2].as<double>()});
      }
    }
  } catch (const YAML::Exception& e) {
    throw Error(path, std::string("bad value: ") + e.what());
  }
  validate(c, path);
  return c;
}

}  // namespace flatnet
