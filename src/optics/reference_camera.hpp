#pragma once
// `flatnet calibrate --references` as one procedure: a camera identified from a few direct captures
// and someone else's reconstructions of them, with every figure its camera file states.
//
//   1. the calibration (optics/calibrate_references.hpp eq. 1, or 1' with a fixed light), from all pairs;
//   2. the leave-one-out check (3 pairs or more): each pair reconstructed from the others' calibration,
//      its correlation with its reference, its leak, and the jackknife of the coded light, sqrt(n - 1)
//      x the rms move of the held-out fits (Efron and Stein, 1981), which sizes data.calibration_error.
//      A mean held-out correlation below 0.5 is refused: such a calibration fitted the pairs, not the camera;
//   3. the light unit: a white capture's measured light (eq. 2), else the prior that the scenes hold
//      --scene-light of the display's white on average, else the references' own units;
//   4. the noise model from what the captures hold beyond the calibration (less its fixed light), the
//      leak threshold raised to what held-out captures leak, and the open light;
//   5. the camera: the given geometry with the absolute Tikhonov regulariser and those keys.
// The command line parses, reads the files and prints; everything decided is here.
#include <array>
#include <optional>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "io/camera_config.hpp"
#include "optics/calibrate_references.hpp"
#include "optics/camera_fit.hpp"

namespace flatnet {

// A capture of a uniform white scene (--white-capture), preprocessed as the pairs are.
struct WhiteCaptureInput {
  std::string name;    // the file as given, for messages and the camera file's header
  double light = 1;    // its light relative to the display's white, in (0, 1000]
  NoiseSample sample;  // its planes, level and saturated share
};

struct ReferenceCameraOptions {
  ReferenceCalibrationOptions fit;
  double lambda = 3e-4;  // relative Tikhonov regulariser, in (0, 1)
  // The scenes' mean light without a white capture (0: none; its range, [0, 1000], is calibrate's flag row's).
  double scene_light = kTypicalSceneLight;
};

enum class LightUnitSource {
  references,     // the references' own units (no white capture, and no prior or no scene with light)
  scene_prior,    // the scenes taken to hold `light` of the display's white on average
  white_capture,  // measured: a white capture of light `light`
};

struct LightUnit {
  LightUnitSource source = LightUnitSource::references;
  double light = 0;               // the white's light, or the prior's
  std::array<double, 4> scale{};  // the references' units were multiplied by this per channel
  std::array<double, 4> level{};  // white capture: its level in the references' units per channel
  double white_residual = -1;     // white capture: the coded light a uniform scene leaves (mean)
  std::string white_name;         // white capture: the file
  bool no_scene_light = false;    // a prior was asked for, and a pair's scene has no positive light
};

struct ReferenceCamera {
  ReferenceCalibration fit;       // in the light unit's units
  std::vector<HeldOutPair> held;  // empty below 3 pairs
  double held_mean = -1;          // mean held-out correlation (< 0: not checked)
  double held_leak = 0;           // the largest leak of a held-out capture
  double held_change = -1;        // the jackknife of the coded light (< 0: not measured)
  LightUnit light;
  NoiseModelFit noise;
  double lambda = 0;              // relative, as given
  double fixed_light_share = -1;  // ||F|| over a capture's mean norm (< 0: no fixed light fitted)
  size_t captures = 0;
  CameraConfig camera;  // the geometry given with what was identified
};

// Steps 1-5 above. `samples[i]` is pair i's capture (its level and saturated share); the options'
// ranges are checked first, and a white capture's saturation before any fit.
ReferenceCamera identify_reference_camera(const std::vector<ReferencePair>& pairs,
                                          const std::vector<NoiseSample>& samples,
                                          const std::optional<WhiteCaptureInput>& white, const CameraConfig& geometry,
                                          const ReferenceCameraOptions& o);

// The camera file's comment: how the calibration was identified and what each figure means.
std::string reference_camera_header(const ReferenceCamera& camera);

// A white capture may hold at most this share of its window at full scale: more, and its level
// understates the light.
constexpr double kWhiteSaturatedAtMost = 1e-3;
// What a uniform scene may leave of a white capture's well-measured coded light (eq. 2's residual,
// the mean over channels): the prototype's twin's white, with light the separable model misses,
// leaves 0.31; captures of 40 photographs through it 0.56-0.85.
constexpr double kWhiteResidualAtMost = 0.45;

}  // namespace flatnet
