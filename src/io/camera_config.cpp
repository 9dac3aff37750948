#include "io/camera_config.hpp"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <functional>
#include <sstream>
#include <type_traits>

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

// One row per camera-file key (the order a camera file states them in): how it is read, how it is
// written (nothing where the file leaves it out), the one check of its range, and what `flatnet
// options --for camera` shows of it. Checks across keys (even raw sizes, the crop inside the plane,
// hot pixels inside the frame, colour_mix's rows and rank) follow the rows in validate().
struct CameraKey {
  CameraKeyDescription shown;  // key, default, range, doc
  std::function<void(const YAML::Node&, CameraConfig&, const std::filesystem::path& path,
                     const std::filesystem::path& base)>
      read;
  std::function<void(const CameraConfig&, std::ostream&)> write;
  std::function<std::string(const CameraConfig&)> problem;  // "" when in range
};

// A number's range: [lo, hi] (lo excluded when lo_open), or 0 where 0 means "unknown / the default
// rule" (zero_off).
struct NumberRange {
  double lo, hi;
  bool lo_open = false, zero_off = false, hi_open = false;
};

std::string number_text(double v) {
  std::ostringstream os;
  os.precision(17);
  os << v;
  return os.str();
}

// A number key: `ref` its member; stated in the file when `stated` says so (always when null).
template <class T>
CameraKey number_key(const char* key, T& (*ref)(CameraConfig&), NumberRange range, const char* range_text,
                     const char* doc, bool (*stated)(const CameraConfig&) = nullptr) {
  static_assert(std::is_arithmetic_v<T>);
  auto value = [ref](const CameraConfig& c) { return ref(const_cast<CameraConfig&>(c)); };
  CameraConfig defaults;
  CameraKey k;
  k.shown = {key, number_text(static_cast<double>(ref(defaults))), range_text, doc};
  k.read = [ref, key](const YAML::Node& y, CameraConfig& c, const std::filesystem::path&,
                      const std::filesystem::path&) { ref(c) = y[key].as<T>(); };
  k.write = [value, key, stated](const CameraConfig& c, std::ostream& os) {
    if (!stated || stated(c)) os << key << ": " << number_text(static_cast<double>(value(c))) << "\n";
  };
  k.problem = [value, key, range, range_text](const CameraConfig& c) -> std::string {
    const auto v = static_cast<double>(value(c));
    const bool in =
        std::isfinite(v) && ((range.zero_off && v == 0) || ((range.lo_open ? v > range.lo : v >= range.lo) &&
                                                            (range.hi_open ? v < range.hi : v <= range.hi)));
    return in ? "" : std::string(key) + " is " + range_text + "; got " + number_text(v);
  };
  return k;
}

// A key with a structure (a text, a list, a path, a mapping): its own reader and writer.
CameraKey structure_key(const char* key, std::string default_text, const char* range_text, const char* doc,
                        decltype(CameraKey::read) read, decltype(CameraKey::write) write) {
  CameraKey k;
  k.shown = {key, std::move(default_text), range_text, doc};
  k.read = std::move(read);
  k.write = write ? std::move(write) : [](const CameraConfig&, std::ostream&) {};
  k.problem = [](const CameraConfig&) { return std::string(); };
  return k;
}

BenchErrors bench_from_node(const YAML::Node& y, const std::filesystem::path& path);

// colour_mix: 4 rows of finite shares, each summing to 1, of rank 3.
void validate_colour_mix(const std::vector<std::array<double, 3>>& mix, const std::filesystem::path& path) {
  require(mix.size() == 4, path, "colour_mix: 4 rows (b, gb, gr, r) of 3 shares (R, G, B)");
  for (const auto& row : mix)
    for (const double v : row)
      require(std::isfinite(v) && std::abs(v) <= 10, path,
              "colour_mix: each share is a finite number within [-10, 10]");
  constexpr double kColourMixSumTolerance = 0.02;
  constexpr const char* kPlaneNames[] = {"b", "gb", "gr", "r"};
  // Each row is a plane's shares of the primaries, scaled to sum 1 (calibrate --dataset writes it so):
  // a row summing to 2 would brighten that plane's scene twice over, silently.
  for (size_t p = 0; p < mix.size(); ++p) {
    const double sum = mix[p][0] + mix[p][1] + mix[p][2];
    require(std::abs(sum - 1) <= kColourMixSumTolerance, path,
            "colour_mix: row " + std::to_string(p + 1) + " (" + std::string(kPlaneNames[p]) + ") sums to " +
                std::to_string(sum) + "; each plane's shares of the primaries sum to 1 (within " +
                std::to_string(kColourMixSumTolerance) +
                "): scale the row, or put the plane's gain in the calibration");
  }
  // The primaries must be recoverable from the planes: the mix has rank 3, not barely.
  const auto smallest = torch::linalg_svdvals(colour_mix_matrix(mix)).min().item<double>();
  require(smallest > 1e-3, path,
          "colour_mix cannot be undone (its smallest singular value is " + std::to_string(smallest) +
              "): two primaries look alike to every plane");
}

bool noise_known(const CameraConfig& c) { return c.knows_noise(); }
bool positive_threshold(const CameraConfig& c) { return c.fit_threshold > 0; }
bool positive_leak(const CameraConfig& c) { return c.leak_threshold > 0; }
bool positive_light(const CameraConfig& c) { return c.open_light > 0; }
bool positive_gamma(const CameraConfig& c) { return c.display_gamma > 0; }

// The frame and the window: what preprocessing needs.
std::vector<CameraKey> geometry_keys() {
  using C = CameraConfig;
  return {
      structure_key(
          "name", "sim", "", "the camera's name (models and reports show it)",
          [](const YAML::Node& y, C& c, auto&, auto&) { c.name = y["name"].as<std::string>(); },
          [](const C& c, std::ostream& os) { os << "name: " << yaml_quoted(c.name) << "\n"; }),
      number_key<int64_t>(
          "raw_height", [](C& c) -> int64_t& { return c.raw.raw_height; }, {2, 65536},
          "even, 2 to 65536 (Bayer mosaic rows)", "raw frame rows"),
      number_key<int64_t>(
          "raw_width", [](C& c) -> int64_t& { return c.raw.raw_width; }, {2, 65536},
          "even, 2 to 65536 (Bayer mosaic columns)", "raw frame columns"),
      number_key<int>(
          "adc_bits", [](C& c) -> int& { return c.raw.adc_bits; }, {1, 16}, "1 to 16",
          "ADC resolution; codes are stored as q * 2^(16 - adc_bits)"),
      number_key<double>(
          "rotation", [](C& c) -> double& { return c.raw.rotation; }, {-kMaxCameraRotation, kMaxCameraRotation},
          "radians, -0.175 to 0.175 (about 10 degrees)",
          "the mask's rotation on the sensor, undone on each Bayer plane about its top-left corner"),
      structure_key(
          "crop", "[6, 10, 500, 620]", "inside the Bayer plane",
          "top, left, height, width of the window within a plane",
          [](const YAML::Node& y, C& c, auto& path, auto&) {
            auto v = y["crop"].as<std::vector<int64_t>>();
            require(v.size() == 4, path, "crop must be [top, left, height, width]");
            std::copy(v.begin(), v.end(), c.raw.crop.begin());
          },
          [](const C& c, std::ostream& os) {
            const auto& g = c.raw.crop;
            os << "crop: [" << g[0] << ", " << g[1] << ", " << g[2] << ", " << g[3] << "]\n";
          }),
      structure_key(
          "centring", "plane", "plane, level, flatnet or none", "how each plane is centred before inversion",
          [](const YAML::Node& y, C& c, auto& path, auto&) {
            c.raw.centring = parse_centring(y["centring"].as<std::string>(), path);
          },
          [](const C& c, std::ostream& os) { os << "centring: " << centring_name(c.raw.centring) << "\n"; }),
      structure_key(
          "hot_pixels", "[]", "at most 100000 [row, col] pairs inside the raw frame",
          "stuck pixels, repaired from their neighbours before anything else",
          [](const YAML::Node& y, C& c, auto& path, auto&) {
            const auto list = y["hot_pixels"];
            require(list.IsSequence(), path, "hot_pixels: expected a list of [row, col] pairs");
            for (const auto& item : list) {
              require(item.IsSequence() && item.size() == 2, path,
                      "hot_pixels: each entry is [row, col] of the raw frame");
              c.raw.hot_pixels.push_back({item[0].as<int64_t>(), item[1].as<int64_t>()});
            }
          },
          [](const C& c, std::ostream& os) {
            const auto& h = c.raw.hot_pixels;
            if (h.empty()) return;
            os << "hot_pixels: [";
            for (size_t i = 0; i < h.size(); ++i) os << (i ? ", " : "") << "[" << h[i][0] << ", " << h[i][1] << "]";
            os << "]\n";
          }),
      number_key<int64_t>(
          "scene_size", [](C& c) -> int64_t& { return c.scene_size; }, {1, 4096}, "1 to 4096",
          "scene / reconstruction side, pixels"),
  };
}

// The calibration and what was measured of the sensor and the light.
std::vector<CameraKey> calibration_keys() {
  using C = CameraConfig;
  return {
      structure_key(
          "calibration", "", "a .mat beside the camera file",
          "FlatNet-layout calibration (P1b..Q1r), relative paths "
          "from the camera file's folder",
          [](const YAML::Node& y, C& c, auto&, auto& base) {
            c.calibration = base / y["calibration"].as<std::string>();
          },
          nullptr),
      structure_key(
          "rig", "", "a .mat beside the camera file", "a simulated camera's true response",
          [](const YAML::Node& y, C& c, auto&, auto& base) { c.rig = base / y["rig"].as<std::string>(); }, nullptr),
      number_key<double>(
          "tikhonov_lambda", [](C& c) -> double& { return c.tikhonov_lambda; }, {0, 1e4, true}, "(0, 1e4]",
          "the calibration's Tikhonov regulariser"),
      number_key<double>(
          "tv_lambda", [](C& c) -> double& { return c.tv_lambda; }, {0, 1e4, true}, "(0, 1e4]", "the TV weight"),
      number_key<double>(
          "noise_gain", [](C& c) -> double& { return c.noise_gain; }, {0, 1, false, false, true}, "[0, 1) full scale",
          "the sensor's noise: variance noise_gain x (level - dark) + noise_floor; 0: unknown", noise_known),
      number_key<double>(
          "noise_floor", [](C& c) -> double& { return c.noise_floor; }, {0, 1, false, false, true}, "[0, 1) full scale",
          "read noise and the ADC's rounding (variance)", noise_known),
      number_key<double>(
          "dark", [](C& c) -> double& { return c.dark; }, {0, 1, false, false, true}, "[0, 1) full scale",
          "the level without light", noise_known),
      number_key<double>(
          "fit_threshold", [](C& c) -> double& { return c.fit_threshold; }, {1, 1e3, false, true},
          "0 (the camera fit's own) or a ratio within [1, 1000]",
          "the camera fit's threshold for an estimated calibration", positive_threshold),
      number_key<double>(
          "leak_threshold", [](C& c) -> double& { return c.leak_threshold; }, {1, 1e3, false, true},
          "0 (the camera fit's own) or a ratio within [1, 1000]",
          "the near-twin test's threshold for an estimated calibration", positive_leak),
      number_key<double>(
          "open_light", [](C& c) -> double& { return c.open_light; }, {0, 1e3, true, true},
          "0 (unknown) or a plane's level per unit of mean scene light, within (0, 1000]",
          "the light every pixel reads whatever the scene", positive_light),
      number_key<double>(
          "display_gamma", [](C& c) -> double& { return c.display_gamma; },
          {kLeastDisplayGamma, kLargestDisplayGamma, false, true}, "0 (the sRGB curve) or a power within [0.5, 3]",
          "how a displayed photograph's value becomes light in the calibration's units", positive_gamma),
      structure_key(
          "colour_mix", "[]", "4 rows of 3 shares, each row summing to 1, rank 3",
          "each Bayer plane's share of the display's primaries (R, G, B)",
          [](const YAML::Node& y, C& c, auto& path, auto&) {
            const auto rows = y["colour_mix"];
            require(rows.IsSequence() && rows.size() == 4, path,
                    "colour_mix: 4 rows (b, gb, gr, r) of 3 shares (R, G, B)");
            for (const auto& row : rows) {
              require(row.IsSequence() && row.size() == 3, path, "colour_mix: each row is 3 shares (R, G, B)");
              c.colour_mix.push_back({row[0].as<double>(), row[1].as<double>(), row[2].as<double>()});
            }
          },
          [](const C& c, std::ostream& os) {
            if (c.colour_mix.empty()) return;
            os << "colour_mix: [";
            for (size_t p = 0; p < c.colour_mix.size(); ++p)
              os << (p ? ", " : "") << "[" << number_text(c.colour_mix[p][0]) << ", " << number_text(c.colour_mix[p][1])
                 << ", " << number_text(c.colour_mix[p][2]) << "]";
            os << "]\n";
          }),
      structure_key(
          "bench", "", "a mapping of bench errors (bench.*)", "a simulated bench camera's errors (simulation only)",
          [](const YAML::Node& y, C& c, auto& path, auto&) { c.bench = bench_from_node(y["bench"], path); }, nullptr),
  };
}

const std::vector<CameraKey>& camera_keys() {
  static const std::vector<CameraKey> keys = [] {
    auto all = geometry_keys();
    for (auto& key : calibration_keys()) all.push_back(std::move(key));
    return all;
  }();
  return keys;
}

// Each key's range (its row), then the rules across keys.
void validate(const CameraConfig& c, const std::filesystem::path& path) {
  for (const auto& key : camera_keys()) {
    const auto problem = key.problem(c);
    require(problem.empty(), path, problem);
  }
  const auto& g = c.raw;
  require(g.raw_height % 2 == 0 && g.raw_width % 2 == 0, path,
          "raw_height and raw_width must be positive and even (Bayer mosaic)");
  require(g.crop[0] >= 0 && g.crop[1] >= 0 && g.crop[2] > 0 && g.crop[3] > 0 &&
              g.crop[0] + g.crop[2] <= g.plane_height() && g.crop[1] + g.crop[3] <= g.plane_width(),
          path,
          "crop [top, left, height, width] must lie inside the " + std::to_string(g.plane_height()) + "x" +
              std::to_string(g.plane_width()) + " Bayer plane");
  require(static_cast<int64_t>(g.hot_pixels.size()) <= kMaxHotPixels, path,
          "hot_pixels lists " + std::to_string(g.hot_pixels.size()) + " pixels; at most " +
              std::to_string(kMaxHotPixels) + " (a sensor with more is broken, not calibrated)");
  for (const auto& [row, col] : g.hot_pixels)
    require(row >= 0 && row < g.raw_height && col >= 0 && col < g.raw_width, path,
            "hot_pixels: [" + std::to_string(row) + ", " + std::to_string(col) + "] lies outside the " +
                std::to_string(g.raw_height) + "x" + std::to_string(g.raw_width) + " raw frame (rows x columns)");
  if (!c.colour_mix.empty()) validate_colour_mix(c.colour_mix, path);
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
  std::ostringstream os;
  for (const auto& key : camera_keys()) key.write(c, os);
  return os.str();
}

namespace {

// The bench: section's keys: each a number within its range (a simulated bench's plausible errors),
// checked by the rule every config number is (core/util.hpp number_problem). hot_pixels, a count, has
// no double member.
struct BenchKey {
  NumberRule rule;
  double BenchErrors::*member;
};

const std::vector<BenchKey>& bench_keys() {
  using B = BenchErrors;
  static const std::vector<BenchKey> keys = {
      {{"crosstalk", 0, 0.5, "a share, 0 to 0.5"}, &B::crosstalk},
      {{"mask_rotation", -0.1, 0.1, "radians, -0.1 to 0.1"}, &B::mask_rotation},
      {{"second_term", 0, 0.5, "a share, 0 to 0.5"}, &B::second_term},
      {{"flicker", 0, 0.5, "0 to 0.5"}, &B::flicker},
      {{"stray_light", 0, 0.5, "full scale, 0 to 0.5"}, &B::stray_light},
      {{"hot_pixels", 0, 1e5, "0 to 100000 pixels"}, nullptr},
      {{"display_shift", -16, 16, "scene pixels, -16 to 16"}, &B::display_shift},
      {{"display_scale", 0.8, 1.25, "0.8 to 1.25"}, &B::display_scale},
      {{"calibration_error", 0, 0.5, "a share of the coded light, 0 to 0.5"}, &B::calibration_error}};
  return keys;
}

BenchErrors bench_from_node(const YAML::Node& y, const std::filesystem::path& path) {
  require(y.IsMap(), path, "bench: expected a mapping of bench errors");
  BenchErrors b;
  const auto& keys = bench_keys();
  for (const auto& kv : y) {
    const auto key = kv.first.as<std::string>(), text = kv.second.as<std::string>();
    const auto row = std::find_if(keys.begin(), keys.end(), [&](const BenchKey& k) { return key == k.rule.name; });
    require(row != keys.end(), path, "unknown bench error 'bench." + printable(key) + "'");
    const auto problem = number_problem(text, row->rule);
    require(problem.empty(), path, "bench." + key + " = " + printable(text) + " " + problem + ": " + row->rule.meaning);
    const double value = std::strtod(text.c_str(), nullptr);
    if (row->member)
      b.*(row->member) = value;
    else
      b.hot_pixels = static_cast<int64_t>(value);
  }
  return b;
}

}  // namespace

std::vector<CameraKeyDescription> camera_file_keys() {
  std::vector<CameraKeyDescription> shown;
  for (const auto& key : camera_keys()) shown.push_back(key.shown);
  const BenchErrors defaults;
  for (const auto& key : bench_keys())
    shown.push_back({std::string("bench.") + key.rule.name,
                     number_text(key.member ? defaults.*(key.member) : static_cast<double>(defaults.hot_pixels)),
                     key.rule.meaning, "a simulated bench's error (simulation only)"});
  return shown;
}

CameraConfig camera_from_node(const YAML::Node& y, const std::filesystem::path& path,
                              const std::filesystem::path& base) {
  CameraConfig c;
  require(y.IsMap(), path, "expected a mapping of camera settings");
  const auto& keys = camera_keys();
  try {
    for (const auto& kv : y) {
      const auto key = kv.first.as<std::string>();
      require(std::any_of(keys.begin(), keys.end(), [&](const CameraKey& k) { return k.shown.key == key; }), path,
              "unknown camera setting '" + printable(key) + "'");
    }
    for (const auto& key : keys)
      if (y[key.shown.key]) key.read(y, c, path, base);
  } catch (const YAML::Exception& e) {
    throw Error(path, std::string("bad value: ") + e.what());
  }
  validate(c, path);
  return c;
}

}  // namespace flatnet
