#pragma once
// What flatnet knows about a camera: sensor layout, the preprocessing its calibration assumes,
// and where its calibration (and, for a simulated camera, its true response) live.
// Loaded from a YAML file (configs/cameras/*.yaml); library code takes these structs, not YAML.
#include <array>
#include <filesystem>
#include <string>
#include <vector>

namespace flatnet {

enum class Centring {
  plane,    // Y - rowmean - colmean + mean of the plane (the camera README's definition)
  flatnet,  // as FlatNet's loader: the added mean is taken over all four planes together
  none,
  // plane centring, then each plane's raw mean added back as its DC: the light level. Plane
  // centring maps every flat capture (a black scene, or a saturated white one) to zeros; a model
  // with model.level_input reads the level and removes it before its inversion.
  level
};

// The largest |rotation| a camera file may state (radians, about 10 degrees). A mask is glued square
// to its sensor to within a few milliradians (FlatNet's prototype: 0.00174); more is a unit mistake
// (degrees for radians), not a camera.
inline constexpr double kMaxCameraRotation = 0.175;
// The most hot pixels a camera file may list: a sensor with more is broken, not calibrated.
inline constexpr int64_t kMaxHotPixels = 100000;
// CameraConfig::display_gamma's range: a display or tone curve's power, not a unit mistake.
inline constexpr double kLeastDisplayGamma = 0.5, kLargestDisplayGamma = 3.0;

// How a raw frame becomes measurement planes (FlatNet's demosaic_raw, made explicit).
struct RawGeometry {
  int64_t raw_height = 1024;                        // raw frame, rows
  int64_t raw_width = 1280;                         // raw frame, columns
  int adc_bits = 10;                                // ADC resolution; codes stored as q * 2^(16-adc_bits)
  double rotation = 0.0;                            // radians, applied to each Bayer plane about its top-left corner
  std::array<int64_t, 4> crop = {6, 10, 500, 620};  // top, left, height, width within a plane
  Centring centring = Centring::plane;
  // Pixels of the raw frame, (row, col), stuck bright (hot) or dark whatever the light: before
  // anything else each is replaced by the mean of its same-colour neighbours (io/raw.hpp
  // repair_hot_pixels). `flatnet calibrate --dataset` finds and lists them (optics/hot_pixels.hpp).
  std::vector<std::array<int64_t, 2>> hot_pixels;
  int64_t plane_height() const { return raw_height / 2; }
  int64_t plane_width() const { return raw_width / 2; }
};

// A real display-capture bench's errors that the reference simulator leaves out (the `bench:` section
// of a simulated camera's file; all 0: none). They are the simulated camera's truth: only simulation
// reads them (optics/bench.hpp), and calibration has to find what they do from the captures.
struct BenchErrors {
  double crosstalk = 0;      // each Bayer plane sees this share of the display's other two primaries
  double mask_rotation = 0;  // radians: the mask's rotation on the sensor, which the geometry does not state
  double second_term = 0;    // a second separable term of the response, relative to the first
  double flicker = 0;        // relative standard deviation of each capture's exposure
  double stray_light = 0;    // a smooth stray-light ramp over the sensor, full-scale units at its brightest
  int64_t hot_pixels = 0;    // raw pixels stuck bright, at fixed places
  double display_shift = 0;  // the photograph shown this many scene pixels off-centre (down and right)
  double display_scale = 1;  // and scaled by this about its centre
  // Each capture's coded light comes through a calibration that errs by this share of that light
  // (iid Gaussian factor errors, redrawn for every capture): the camera differs from what its
  // calibration says (the size `calibrate --references`'s leave-one-out shows).
  double calibration_error = 0;
  bool any() const {
    return crosstalk != 0 || mask_rotation != 0 || second_term != 0 || flicker != 0 || stray_light != 0 ||
           hot_pixels != 0 || display_shift != 0 || display_scale != 1 || calibration_error != 0;
  }
};

struct CameraConfig {
  std::string name = "sim";
  RawGeometry raw;
  int64_t scene_size = 256;           // scene / reconstruction side, pixels
  std::filesystem::path calibration;  // FlatNet-layout calib .mat (P1b.. Q1r); may be empty
  std::filesystem::path rig;          // true response (simulated cameras only); may be empty
  double tikhonov_lambda = 1e-4;      // default regulariser for this calibration
  double tv_lambda = 1e-4;            // default TV weight
  // The sensor's noise, in full-scale units (raw / (2^16 - 1)): a pixel reading v has variance
  // noise_gain * (v - dark) + noise_floor (photon noise of a Poisson count, then read noise and the
  // ADC's rounding). noise_gain = 1 / full well; noise_floor = (read noise / full well)^2 + lsb^2/12.
  // 0 = unknown. `flatnet calibrate --dataset` measures them; the camera fit (optics/camera_fit) needs them.
  double noise_gain = 0, noise_floor = 0, dark = 0;
  // The camera fit's threshold when the calibration is itself an estimate with error (0: the
  // statistic's own, set by chance alone). A calibration identified from display-capture pairs
  // leaves 10-15 % of each capture's coded light unexplained, and how much lands outside its span
  // varies from scene to scene; `flatnet calibrate --dataset` measures that spread on its own pairs
  // and writes the threshold that covers it.
  double fit_threshold = 0;
  // The same for the camera fit's near-twin test (optics/camera_fit.hpp, coded_leak): an estimated
  // calibration's error is itself structured, so its own captures show a leak; calibrate --dataset
  // writes the threshold its pairs need. 0: noise alone sets it.
  double leak_threshold = 0;
  // The light every pixel reads whatever the scene, through the mask's open part and as stray light:
  // a plane's mean level per unit of the scene's mean linear light (level = dark + open_light *
  // mean(X)). 0 = unknown. `flatnet calibrate --references` measures it; with the noise model it lets
  // a camera known only from its calibration be simulated through it (optics/camera.hpp calibration_rig).
  double open_light = 0;
  // How a displayed photograph's value v (0..1) becomes light in the calibration's scene units:
  // v^display_gamma, or the sRGB curve when 0. A calibration measured in linear light (Hadamard
  // patterns, display-capture pairs) takes sRGB; one identified from someone else's reconstructions
  // is in their tone, which may not be linear (FlatNet's prototype: docs/own-camera.md). Simulation
  // and training show photographs through it, and reconstructions are displayed through its inverse.
  double display_gamma = 0;
  // The share of each display primary (R, G, B) that each Bayer plane (b, gb, gr, r) sees: colour
  // filters and a display's spectra overlap. Each row sums to 1 (a grey scene gives every plane its
  // level). Empty: none (b sees B alone, gb and gr G, r R). `flatnet calibrate --dataset` identifies
  // it with the factors; Tikhonov and TV undo it (io/image.hpp unmix_primaries).
  std::vector<std::array<double, 3>> colour_mix;
  BenchErrors bench;  // a simulated bench camera's errors (simulation only; not in model files)
  bool knows_noise() const { return noise_gain > 0; }
};

// Reads a camera YAML file; relative paths inside it are resolved against the file's folder.
// A `.mat` path is taken as a rig file: geometry from its `crop` and `adc_bits`, the rest default.
CameraConfig load_camera_config(const std::filesystem::path& path);

// The same settings from YAML text (as embedded in a model file); `where` names the source in errors.
CameraConfig camera_from_yaml_text(const std::string& text, const std::filesystem::path& where);
// Every key a camera file may hold (bench.* included), with its default, its one range and what it
// is: what `flatnet options --for camera` prints.
struct CameraKeyDescription {
  std::string key, default_text, range, doc;
};
std::vector<CameraKeyDescription> camera_file_keys();
// The preprocessing settings (geometry, scene size, lambdas; no file paths) as YAML text.
std::string camera_geometry_yaml(const CameraConfig& camera);
// A camera file made from data (`calibrate`): `comment`, then `camera`'s settings without its rig,
// naming `calibration_name` (a file beside it). Read back as every reader reads it before it is
// returned, so flatnet never writes a camera file it refuses to read: errors name `where` and the
// setting refused.
std::string camera_file_text(const CameraConfig& camera, const std::string& calibration_name,
                             const std::string& comment, const std::filesystem::path& where);

// The project's reference camera (configs/cameras/sim.yaml) in the source tree.
std::filesystem::path default_camera_path();

Centring parse_centring(const std::string& s, const std::filesystem::path& where);
std::string centring_name(Centring c);

}  // namespace flatnet
