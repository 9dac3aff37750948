#pragma once
// FlatCam calibration (Asif et al., "FlatCam", IEEE TCI 2017, sec. IV): show separable patterns,
// capture them, and recover P and Q from the rank-1 structure of each capture.
//
// Row patterns X = ((1 +- h_k)/2) 1^T and column patterns X = 1 ((1 +- h_k)/2)^T, with h_k the
// columns of an NxN Hadamard matrix. After preprocessing, the difference of a +/- pair is
//   D_k^row = P h_k (Q 1)^T,   D_k^col = (P 1) (Q h_k)^T,
// rank 1 with a factor common to the whole set (the light through the mask's open part cancels,
// since sum(h_k) = 0 for k > 0). The common factors a = P 1 and b = Q 1 come from the top singular
// vectors of the stacked differences and the scale of the all-white capture; then
//   P h_k = D_k^row b / |b|^2,   Q h_k = D_k^col^T a / |a|^2,   P = [P h_k] H^T / N.
#include <functional>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "optics/camera.hpp"

namespace flatnet {

struct CalibrationPattern {
  std::string name;     // file stem, e.g. "row_005_pos"
  torch::Tensor image;  // {N,N} float32 display values (sRGB): 0 or level_code / 255
};

// Patterns are shown at a display level below full white: a full-white scene saturates a FlatCam
// (the reference camera reaches 2.3x full scale). 160 (sRGB) is 0.35 in linear light.
constexpr int kDefaultPatternLevel = 160;
double pattern_level_linear(int level_code);  // sRGB code -> linear light

// The 4N patterns for an N-pixel scene (N a power of two), in display order.
std::vector<CalibrationPattern> calibration_patterns(int64_t scene_size, int level_code = kDefaultPatternLevel);

// `capture(name)` returns the preprocessed planes {4,h,w} of the capture of pattern `name`, shown
// at `level_code`; the estimate is scaled to a unit (linear 1.0) scene, as FlatNet's calibration is.
Calibration estimate_calibration(int64_t scene_size, const std::function<torch::Tensor(const std::string&)>& capture,
                                 int level_code = kDefaultPatternLevel, bool show_progress = true);

// Pattern captures through a rig: the display shows pattern `name` (sRGB -> linear, all colours),
// the sensor reads `average` frames (noisy or not), and their mean is preprocessed for `g`.
std::function<torch::Tensor(const std::string&)> rig_pattern_capture(const Rig& rig, const RawGeometry& g,
                                                                     int level_code, bool noise, int average,
                                                                     at::Generator gen);

// Relative error of an estimate against a truth, insensitive to the scale split between P and Q
// (P*s, Q/s is the same camera): each factor is compared after its best scalar fit.
struct CalibrationError {
  double p = 0, q = 0;  // ||a P_est - P|| / ||P||, averaged over channels
  double forward = 0;   // ||P_e X Q_e^T - P X Q^T|| / ||P X Q^T|| on random scenes, or on `scene`
};
// `scene` {4,N,N}: the planes the forward error is measured on (undefined: uniform random ones).
CalibrationError calibration_error(const Calibration& estimate, const Calibration& truth,
                                   const torch::Tensor& scene = {});

}  // namespace flatnet
