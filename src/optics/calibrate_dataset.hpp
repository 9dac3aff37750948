#pragma once
// A FlatCam's calibration identified from the display-capture pairs its users already hold, instead
// of 4N Hadamard pattern captures (optics/calibrate.hpp).
//
// After double-centring, each Bayer channel c of a capture of scene X (linear light, {N,N}) is
//   Y = P X Q^T + s(X) a b^T + E,        s(X) = sum of X's pixels,                         (1)
// the separable coded part (FlatNet thesis eq. 2.2) plus the light through the mask's open part,
// whose smooth vignetting survives the centring as one rank-1 image scaled by the scene's total
// light (camera README, "The true response"). Split each scene into its mean and the rest,
// X = (s / N^2) 1 1^T + Xz: then (1) reads
//   Y = P Xz Q^T + s M + E,              M = P 1 1^T Q^T / N^2 + a b^T,                    (2)
// where M, the camera's response to a uniform scene, is a free {rows,cols} matrix. (2) is bilinear
// in P and Q and linear in M: for fixed Q, P and M solve one least-squares problem shared by all
// rows ("500 + 620 small problems" with one Gram matrix), M eliminated in closed form; then Q for
// fixed P. Alternating least squares converges in a few passes to the calibration, up to the scale
// split P*k, Q/k that no capture can tell apart. (Fitting a and b as factors instead converges
// slowly: s a b^T and the coded part's mean both scale with s.) With Z_i = Xz_i Q^T, the sums
//   A = sum Z Z^T, B = sum Y Z^T, Sz = sum s Z, Sy = sum s Y, S2 = sum s^2
// give P = (B - Sy Sz^T / S2)(A - Sz Sz^T / S2 + rI)^-1 and M = (Sy - P Sz) / S2.
// Free factors have 128,000 unknowns each (FlatNet's P), more than a few hundred noisy photographs
// pin down: their fine detail, which photographs hardly show, stays unknown. So after `free_passes`
// free steps each factor is fitted with the shift structure of a FlatCam (optics/shift_structure.hpp:
// column j is column 0's shadow moved by j * shift pixels), about 1,000 unknowns, the shift found from
// the data; `FactorStructure::Free` keeps the free fit for a camera without that structure.
// The verdict on the structure: once both factors have searched their shift twice (each search
// sharper once the other factor is structured), the structured model's residual over the pairs is
// set against the free model's before it, each as the coded energy it explains beyond M alone, less
// sigma^2 per parameter (what fitting the noise alone explains). Below 0.3 the structure is rejected
// and the free model is taken up again; so is a structure whose shift search ended at an edge of its
// range (no minimum found inside it). (Judged at the first structured step instead, with Q still
// free, a bench camera's moving shadow was rejected: the free Q's errors, which only a free P
// follows, left the structured P 0.2-0.28 of the free one's share from 150 pairs, issue 94.)
// Colour cross-talk: a Bayer plane sees a mix of the display's primaries, X_c = sum_k m_ck X_k
// (k in R, G, B; a filter passes some of its neighbours' light, a display's primaries overlap). For
// fixed P, Q and M, (2) is linear in plane c's three shares: Y_c ~ sum_k m_ck (P_c Xz_k Q_c^T + s_k M_c),
// a 3x3 least-squares problem per plane over the pairs; each row is then scaled to sum 1 (the scale
// is P's). `identify_mix` fits it after every pass from the first `mix_pairs` pairs, and the next pass
// fits P and Q to the mixed scenes. Scenes whose gb and gr planes differ (not made from RGB) are
// left unmixed.
// The pairs are streamed: those that fit the memory budget stay decoded, the rest are read again in
// every pass, so thousands of pairs run in bounded memory.
#include <array>
#include <cstdint>
#include <functional>

#include <torch/torch.h>

#include "optics/camera.hpp"
#include "optics/shift_structure.hpp"

namespace flatnet {

// Below this share of what free factors explain, the structure is rejected (the header's verdict):
// a camera whose mask is no moving shadow (random factors) leaves it near 0.16.
constexpr double kStructureExplainsAtLeast = 0.3;

struct CapturePair {
  torch::Tensor meas;    // {4,rows,cols} preprocessed (double-centred) capture planes
  torch::Tensor scene;   // {4,N,N} the scene shown, linear light, per Bayer channel
  torch::Tensor level;   // {4} the window's mean raw value per plane (full scale); optional
  double saturated = 0;  // share of the window's pixels at full scale (optics/camera_fit.hpp at_full_scale)
};

enum class FactorStructure { Shift, Free };

struct DatasetCalibrationOptions {
  int iterations = 40;              // alternating passes at most (each reads the pairs twice)
  double tolerance = 1e-4;          // stop when the relative residual improves by less than this
  double ridge = 1e-6;              // r above for the first step, relative to the Gram matrix's mean diagonal;
                                    // then r = noise variance / mean square of the factor (a Gaussian prior)
  uint64_t seed = 0;                // the random start of Q
  int64_t cache_bytes = 2ll << 30;  // decoded pairs kept in memory; the rest are re-read
  bool progress = true;
  FactorStructure structure = FactorStructure::Shift;
  int free_passes = 2;             // free steps before the structured ones (they give the shift search its start)
  std::array<double, 2> shifts{};  // rows, columns: shifts already known, fitted without a search (0: search)
  bool judge_structure = true;     // false: keep the structure whatever its share (the rotation search
                                   // reads the structured model's residual; the main fit judges)
  bool identify_mix = true;        // fit each plane's shares of the primaries (else b sees B alone, ...)
  int64_t mix_pairs = 128;         // the pairs the mix is fitted to
  ShiftFitOptions shift;
};

struct DatasetCalibration {
  Calibration calib;                 // P {4,rows,N}, Q {4,cols,N}, float64
  torch::Tensor uniform_response;    // M {4,rows,cols}: the planes a uniform unit scene gives, per unit of s
  torch::Tensor colour_mix;          // {4,3} float64: plane (b, gb, gr, r) by primary (R, G, B), rows summing to 1;
                                     // undefined when not identified
  std::array<double, 4> residual{};  // ||Y - model (2)|| / ||Y|| per channel over all pairs (b, gb, gr, r)
  // The sensor's noise (when the pairs carry levels), from the first pairs' energy outside the
  // calibration's span against their light level, as the camera fit measures it: variance per
  // pixel = noise_gain * (level - dark) + noise_floor.
  double noise_gain = 0, noise_floor = 0, dark = 0;
  double fit_threshold = 0;   // the camera fit's threshold that covers the pairs' own spread (CameraConfig)
  double leak_threshold = 0;  // the same for the near-twin test (coded_leak); 0 where it is not measurable
  int64_t pairs = 0;
  int iterations = 0;
  // The shadow's move per scene pixel, in sensor pixels (signed), when the fit is structured; else 0.
  double shift_rows = 0, shift_cols = 0;
  // The coded energy the structured model explains over what the free model explains (the header's
  // verdict); below 0.3 the structure is rejected and free factors are fitted.
  double structure_explains = 0;
  bool structure_rejected = false;
  // Each axis's structured factor against a free one on the same step, at its second search (rows:
  // P with Q structured; columns: Q with P structured): which axis's shift the data do not bear out.
  std::array<double, 2> axis_explains{};
  std::array<double, 2> searched_shifts{};  // rows, columns: what the searches found, kept or not
  // rows, columns: the search ended in the outermost grid step of its range (no minimum inside it);
  // either rejects the structure.
  std::array<bool, 2> shift_at_edge{};
};

// Scene planes {4,N,N} (b, gb, gr, r) as each Bayer plane sees them through a colour mix {4,3}.
torch::Tensor scene_through_mix(const torch::Tensor& scene, const torch::Tensor& mix);

// Fits (2) to `count` pairs read by `load(i)`. Errors name the pair's index when its planes are not
// {4,rows,cols} and {4,N,N}, or hold NaN.
DatasetCalibration calibrate_from_pairs(int64_t count, const std::function<CapturePair(int64_t)>& load, int64_t rows,
                                        int64_t cols, int64_t scene, const DatasetCalibrationOptions& options);

}  // namespace flatnet
