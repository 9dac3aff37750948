#pragma once
// A FlatCam's calibration recovered from a handful of direct captures and someone else's
// reconstructions of them: "you lost the calibration, but you kept a few reconstructions".
//
// A reconstruction R_i made with the lost calibration is, up to its maker's scaling, the scene the
// camera saw. Per Bayer channel, with the captures preprocessed as for inference (rotation, crop,
// double-centring: the centring C removes each factor's column means),
//   Y_i = C P (a_i R_i + b_i 1 1^T) Q^T C + E_i,                                              (1)
// a gain a_i and offset b_i per pair and channel (the maker's normalisation, unknown), P and Q each
// one profile moved by a fixed shift per scene pixel (optics/shift_structure.hpp eq. 1): about
// 1,400 unknowns per channel where free factors have 287,000, so three pairs identify it.
// (1) is fitted by alternation: P's profile for fixed Q (an exact least-squares solve,
// solve_shift_factor), then Q's, then each pair's (a_i, b_i); the mean gain is held at 1, so P and Q
// reconstruct in the references' units. The shifts are searched first on 2x2-binned pairs (a grid
// over both signs of each axis, from 0.2 to 4 sensor pixels per scene pixel by default, each point a
// converged fit of both structured factors from a random start), then refined at full resolution.
// (A start from free factors misleads the search with three pairs: their errors choose the shift.)
//
// With few pairs the structure cannot be judged against free factors (which fit the pairs they are
// given almost exactly); it is judged on held-out pairs instead: leave_one_out calibrates from all
// pairs but one and reconstructs that one (Tikhonov, thesis eq. 2.6), scored by its Pearson
// correlation with the reference per channel (an affine match: the scale and offset are free),
// leaving out the reference's pixels clipped at zero (their true value is unknown).
#include <array>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "optics/camera.hpp"
#include "optics/separable_inverse.hpp"
#include "optics/shift_structure.hpp"

namespace flatnet {

struct ReferencePair {
  std::string name;         // for messages and the held-out table
  torch::Tensor meas;       // {4,rows,cols} preprocessed capture planes (b, gb, gr, r)
  torch::Tensor reference;  // {4,N,N} the reference reconstruction per Bayer channel, its own units
};

struct ReferenceCalibrationOptions {
  // Fit (1) with a fixed light F, the same on every capture whatever the scene (flare, stray light
  // from outside the display, a sensor's fixed offsets):
  //   Y_i = F + C P (a_i R_i + b_i 1 1^T) Q^T C + E_i.                                      (1')
  // F is free per plane, so the factors are fitted on the pairs' differences from their mean (F
  // eliminated exactly: F = mean_i (Y_i - model_i)); F holds none of a uniform scene's shadow (the
  // gauge that splits F from the offsets b_i, which it would otherwise absorb). Needs 2 pairs at least.
  // Off by default: F estimated from n captures holds 1/n of their noise and of what else they share,
  // and a new capture less F carries it (docs/results/own-camera.md, "Twins that are cameras").
  bool fixed_light = false;
  // Fit the four Bayer planes' profiles as one mask per axis seen through a short kernel per plane
  // (optics/shift_structure.hpp eq. 3: each plane's sub-pixel offset, blur and gain), instead of a
  // profile per plane. `mask_taps` samples per kernel (odd, 3 to 15).
  bool shared_mask = false;
  int mask_taps = 5;
  int passes = 6;               // alternating passes (P, Q, gains)
  int search_passes = 2;        // passes 2 and 3 refine each axis's shift (within 3 %); the others keep it
  uint64_t seed = 0;            // the random profiles that start each trial fit
  ShiftFitOptions shift = [] {  // the search's range and final tolerance
    ShiftFitOptions o;
    o.min_shift = 0.2;
    o.max_shift = 4.0;
    return o;
  }();
  bool progress = true;
};

struct ReferenceCalibration {
  Calibration calib;  // P {4,rows,N}, Q {4,cols,N} (centred), float64; fixed_light F of (1') when fitted
  double shift_rows = 0, shift_cols = 0;           // sensor pixels per scene row / column, signed
  torch::Tensor profile_rows, profile_cols;        // {4,L}: P and Q as profiles (save_shift_calibration)
  torch::Tensor kernels_rows, kernels_cols;        // {4,taps} with shared_mask: each plane's kernel of eq. 3
  std::array<double, 4> residual{};                // ||Y - model (1)|| / ||Y|| per channel over the pairs
  std::vector<std::array<double, 8>> gain_offset;  // per pair: a_b, a_gb, a_gr, a_r, b_b, ..., b_r
  std::vector<std::array<double, 4>> scene_means;  // per pair and channel: the mean of a R + b, P's units
};

// One line for the camera file: with shared_mask, each plane's kernel as the offset (its centroid) and
// blur (its rms width) it gives the mask's shadow, per axis, in sensor pixels.
std::string describe_shared_mask(const ReferenceCalibration& fit);

// Fits (1). Errors name the pair when its planes have the wrong size, hold NaN, or carry no signal.
ReferenceCalibration calibrate_from_references(const std::vector<ReferencePair>& pairs,
                                               const ReferenceCalibrationOptions& options);

// The light every pixel reads whatever the scene (CameraConfig::open_light): each plane's level less
// the dark level against its scene's mean in the calibration's units (fit.scene_means, a R + b of
// eq. 1), one slope through zero by least squares over pairs and planes. levels: {4} per pair, the
// window's mean raw value. 0 when no positive, finite slope is found.
double open_light_of(const std::vector<torch::Tensor>& levels, const ReferenceCalibration& fit, double dark);
// ---- The light unit, from one capture of a white scene ------------------------------------------
// A calibration identified from someone else's reconstructions is in their units, and a min-max
// stretched picture says nothing of the scene's light: pictures made through it come out as bright as
// the references, not as the scene (the prototype's twin: 2.1x its light, docs/own-camera.md). One
// capture of a uniform scene of known light E (the display's white filling the view: E = 1) fixes
// the unit. Its double-centred planes are, per channel, eq. (1) with R = 1:
//   Y_white = m_c C P 1 1^T Q^T C + E,                                                     (2)
// so m_c, the white's light in the calibration's units, is one least-squares number per channel, and
// the scene's light is X = (E / m_c) X_cal: Y = (P / sqrt(s)) X (Q / sqrt(s))^T with s = E / m_c.
struct WhiteFrameFit {
  std::array<double, 4> level{};     // m_c: the white scene's light in the calibration's units
  std::array<double, 4> residual{};  // ||Y - m_c U_c|| / ||Y||: what a uniform scene does not explain
};
// planes {4,rows,cols}: the white capture, preprocessed as the pairs were (double-centred, no level).
// Fitted on the singular pairs above sqrt(lambda), lambda relative as absolute_tikhonov_lambda's.
WhiteFrameFit fit_white_frame(const torch::Tensor& planes, const Calibration& calib, double relative_lambda);
// The scene's values scaled per channel, X = scale_c X_cal: factors and profiles / sqrt(scale_c), the
// pairs' gains, offsets and scene means x scale_c. Pictures through it show the scene's light.
void rescale_scene_units(ReferenceCalibration& fit, const std::array<double, 4>& scale);
// ---- The light unit without a white capture: a prior on the scenes ------------------------------
// Nothing in the pairs fixes the unit, so a prior does: the pairs' scenes (scene_means, the mean over
// channels) hold, on the geometric mean over pairs, `light` of the display's white. The one scale for
// every channel that gives them that (the references' colour balance is kept), for rescale_scene_units;
// 0 when a pair's scene has no positive, finite mean light.
double typical_scene_scale(const ReferenceCalibration& fit, double light);
// The prior's default (`calibrate --scene-light`): a typical photograph of the training set (mean linear
// light 0.220, the geometric mean over 400 of ../shared/data/images/train, sRGB decoded) at 0.287 of the
// display's light, the centre of the exposures the prototype's recipe trains with
// (configs/prototype_transpose.yaml: 0.15-0.55, log-uniform). docs/own-camera.md "The light unit".
constexpr double kTypicalSceneLight = 0.063;

// Pearson correlation per channel of a reconstruction {4,N,N} with a reference {4,N,N}, over the
// reference's pixels above zero.
std::array<double, 4> reference_correlation(const torch::Tensor& reconstruction, const torch::Tensor& reference);

// The Tikhonov lambda (eq. 2.6's, absolute) that is `relative` of the largest squared product of the
// factors' singular values: a calibration in any units regularised alike.
double absolute_tikhonov_lambda(const SeparableInverse& inverse, double relative);

struct HeldOutPair {
  std::string name;
  std::array<double, 4> correlation{};    // b, gb, gr, r
  double shift_rows = 0, shift_cols = 0;  // the shifts the other pairs chose
  double leak = 0;  // its coded leak against their calibration (optics/camera_fit.hpp); 0: not measurable
  // How far the others' calibration lies from the whole one's (< 0: not given): each factor, scaled to
  // fit (calibration_error), and the coded light it predicts of this pair's scene (its reference),
  // ||P' X Q'^T - P X Q^T|| / ||P X Q^T||: the calibration's own uncertainty where scenes put their
  // light (calibrate's jackknife of these sets data.calibration_error's size).
  double change_p = -1, change_q = -1, change_coded = -1;
};

// Each pair reconstructed (Tikhonov with `lambda`, relative as the camera file's tikhonov_lambda)
// from a calibration of the others. Needs at least 3 pairs.
// With `whole` (the calibration from all pairs), each held-out fit's distance from it too.
std::vector<HeldOutPair> leave_one_out(const std::vector<ReferencePair>& pairs, double lambda,
                                       const ReferenceCalibrationOptions& options, const Calibration* whole = nullptr);

}  // namespace flatnet
