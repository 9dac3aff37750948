#pragma once
// The FlatCam camera model: its true response (a "rig", for simulation only) and its
// calibration (what reconstruction uses). Physics in one place: the simulator, the calibration
// procedure, the tests and the benchmarks all call these functions.
#include <filesystem>
#include <optional>

#include <torch/torch.h>

#include "io/camera_config.hpp"

namespace flatnet {

// True response of a separable FlatCam, per Bayer channel c in (b, gb, gr, r), on the whole plane:
//   S_c = gain_c * ( PhiL_c X_c PhiR_c^T + vig_rows vig_cols^T * sum(X_c) )      (full-scale units)
// The second term is the light through the open half of the mask, which carries no code.
struct Calibration;

struct Rig {
  torch::Tensor phil;        // {4, plane_h, N} float32
  torch::Tensor phir;        // {4, plane_w, N}
  torch::Tensor gain;        // {4}
  torch::Tensor vig_rows;    // {plane_h}
  torch::Tensor vig_cols;    // {plane_w}
  double full_well = 40000;  // electrons at full scale
  double read_noise = 4;     // electrons, standard deviation
  double dark = 0.02;        // full-scale units
  int adc_bits = 10;
  BenchErrors bench;  // a simulated bench's errors (optics/bench.hpp; none by default)
  // Light on the sensor whatever the scene (a calibration's fixed light, calibration_rig), added to
  // every capture's signal: {4, plane_h, plane_w} float32, or undefined: none.
  torch::Tensor fixed_light{};
  double display_gamma = 0;  // how a displayed photograph becomes light (CameraConfig::display_gamma)
  int64_t scene_size() const { return phil.size(2); }
};

// Reads rig.mat (PhiL_c, PhiR_c, gain_c, vig_rows, vig_cols, full_well, read_noise, dark, adc_bits).
Rig load_rig(const std::filesystem::path& path);
// The camera's rig (camera.rig), checked against the camera that names it: its scene size and its
// planes' size (the crop) must agree, or the error names both files.
// A camera with no rig but with its noise model and open_light (a real camera, calibrated) is
// simulated through its calibration instead (calibration_rig); other cameras with no rig are an error.
Rig load_camera_rig(const CameraConfig& camera);
// Whether load_camera_rig has something to simulate with, and the file it reads (the rig, or the
// calibration a calibration_rig is made from): recorded with simulated data.
bool can_simulate(const CameraConfig& camera);
std::filesystem::path simulation_source(const CameraConfig& camera);
// A rig made from a calibration (P, Q of the camera's window, centred as calibrations are) and the
// camera file's measurements: the coded light P X Q^T in the crop's rows and columns, the open
// part's uniform light open_light * mean(X) over the whole plane, and a sensor whose photon and read
// noise give the camera's noise model (full well = 1 / noise_gain; read noise from noise_floor less
// the ADC's rounding), and the calibration's fixed light, if it has one, on every capture (in the
// window; it is double-centred, so the planes' level is unchanged). Simulated captures are then what
// the calibration and the noise model predict: what the calibration misses (its error, non-separable light) is not in
// them. The mask's rotation is not undone: preprocessing rotates the simulated planes by the camera's small angle too
// (0.5 pixel at the window's edge for FlatNet's prototype); its interpolation averages noise away, which the sensor's
// noise here makes up for, so that the preprocessed planes carry the noise model's variance.
Rig calibration_rig(const Calibration& calib, const CameraConfig& camera);

// Noise-free expected signal for linear-light scene planes. {B,4,N,N} -> {B,4,plane_h,plane_w}.
torch::Tensor expected_signal(const Rig& rig, const torch::Tensor& scene_planes);

// Sensor noise and ADC: electrons = Poisson(max(S,0) * full_well) + Normal(0, read_noise);
// signal = electrons / full_well + dark; q = clip(round(signal * (2^bits - 1)), 0, 2^bits - 1).
// With noise off the signal is S + dark. Returns integer ADC codes, same shape as S.
// Photon counts: Poisson(mean), exact below 1000 electrons, normal approximation above.
torch::Tensor photon_electrons(const torch::Tensor& mean, c10::optional<at::Generator> gen = c10::nullopt);

torch::Tensor sensor_readout(const Rig& rig, const torch::Tensor& signal, bool noise,
                             c10::optional<at::Generator> gen = c10::nullopt);

// Linear-light scene {3,N,N} (1 = display white; may exceed 1) -> stored 16-bit raw frame {2h,2w} int32.
torch::Tensor simulate_raw_linear(const Rig& rig, const torch::Tensor& scene_linear, bool noise,
                                  c10::optional<at::Generator> gen = c10::nullopt);
// sRGB scene {3,N,N} in [0,1] (as shown on the monitor) -> stored 16-bit raw frame {2h,2w} int32.
torch::Tensor simulate_raw(const Rig& rig, const torch::Tensor& scene_srgb, bool noise,
                           c10::optional<at::Generator> gen = c10::nullopt);

// The whole capture chain as one differentiable function, for learning a camera's codes with the
// network that reconstructs its captures (train/codesign.hpp): linear-light scenes {B,3,N,N} ->
// preprocessed planes {B,4,crop_h,crop_w}, the planes `preprocess_raw(simulate_raw_linear(...))`
// gives. Shot noise is the reparameterised Gaussian approximation of Poisson everywhere
// (photon_electrons samples exactly below 1000 electrons), and the ADC's rounding passes
// gradients straight through (its clipping does not). Geometries with a rotation are refused.
torch::Tensor capture_planes(const Rig& rig, const torch::Tensor& scene_linear, const RawGeometry& geometry, bool noise,
                             at::Generator& gen);

// A calibration in FlatNet's layout: after preprocessing, Y_c ~= P_c X_c Q_c^T.
struct Calibration {
  torch::Tensor P;  // {4, crop_h, N} float64 (P1b, P1gb, P1gr, P1r)
  torch::Tensor Q;  // {4, crop_w, N} float64 (Q1b, ...)
  // The light every capture holds whatever the scene (flare, stray light: `calibrate --references`
  // fits it, optics/calibrate_references.hpp eq. 1'), double-centred as the planes are:
  // Y_c = F_c + P_c X_c Q_c^T. {4, crop_h, crop_w} float64 (fixed_light_b, ...), or undefined: none.
  // Classical reconstruction subtracts it before inverting (without_fixed_light).
  torch::Tensor fixed_light{};
};

// Planes {...,4,h,w} (their level removed) less a fixed light {4,h,w} (Calibration::fixed_light), in
// the planes' type; unchanged when the fixed light is undefined.
torch::Tensor without_fixed_light(const torch::Tensor& planes, const torch::Tensor& fixed_light);

extern const std::array<const char*, 4> kChannelNames;  // b, gb, gr, r
// The index of a channel name in kChannelNames (model.inversion.channel); an error names the key.
int channel_index(const std::string& name);

// Reads P1b..P1r and Q1b..Q1r; checks they match the geometry's crop and scene size.
Calibration load_calibration(const std::filesystem::path& path, const CameraConfig& camera);
void save_calibration(const std::filesystem::path& path, const Calibration& calib);
// A shift-structured calibration as its profiles {4,L} and shifts (kilobytes instead of megabytes);
// load_calibration expands it. Variables: profile_rows, profile_cols, shift_rows, shift_cols.
// With `fixed_light` {4,h,w} defined, it is written too (fixed_light_b, ...).
void save_shift_calibration(const std::filesystem::path& path, const torch::Tensor& profile_rows,
                            const torch::Tensor& profile_cols, double shift_rows, double shift_cols,
                            const torch::Tensor& fixed_light = {});

// The calibration a perfect procedure would find from this rig: the cropped, double-centred
// response (P = gain * C PhiL_window, Q = C PhiR_window). Used as ground truth in tests.
Calibration ideal_calibration(const Rig& rig, const RawGeometry& g);

}  // namespace flatnet
