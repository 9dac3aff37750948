#pragma once
// Test-time adaptation (issue 90 #4): a model meets a real camera's captures with no ground truth,
// so it is fine-tuned on the captures themselves for a few steps before it reconstructs them.
//
// Only the enhancer (theta) moves: the first stage is the camera's own inversion. The loss is the
// captures' own: how far each picture f_theta(y) is from its capture on the singular
// pairs the camera measures above its noise (DataConsistency::disagreement, relative to the
// capture's energy there), plus a penalty that keeps the weights near the shipped ones theta_0
// (L2-SP, Li et al. 2018), relative to their size:
//   L(theta) = mean_k [ d(y_k, f_theta(y_k)) + beta (m(f_theta(y_k)) / m(f_theta_0(y_k)) - 1)^2 ]
//              + mu ||theta - theta_0||^2 / ||theta_0||^2,                                          (1)
// m the picture's mean value: the double-centred capture holds no light level and d fits an exposure
// per capture, so nothing in d fixes the picture's brightness, and left free it drifts (beta 0: the
// prototype's simulated held-out captures came out 1.11x brighter after 30 steps at 1e-4).
// The batch norms keep their running statistics (eval mode): a handful of captures has none of its own.
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "nn/generator.hpp"

namespace flatnet {

class DataConsistency;  // recon/data_consistency.hpp

struct AdaptationOptions {
  int64_t steps = 0;       // Adam steps on (1); 0: off
  int64_t batch = 4;       // captures per step, taken in turn
  double lr = 1e-4;        // Adam's rate
  double anchor = 1e3;     // mu of (1)
  double brightness = 10;  // beta of (1)
  int64_t captures = 32;   // at most this many captures adapt the model, evenly spread over those given
  bool bf16 = false;       // the enhancer under bf16 autocast (weights and Adam's state stay fp32)
};

// Throws naming the option when a value is outside its range.
void check_adaptation_options(const AdaptationOptions& options);

struct AdaptationReport {
  int64_t steps = 0, captures = 0;
  double disagreement_before = 0, disagreement_after = 0;  // (1)'s first term over the captures used
  double distance = 0;  // ||theta - theta_0|| / ||theta_0|| at the end (the enhancer's)
  double seconds = 0;
  std::string summary() const;  // one line for the log
};

// The captures that adapt the model: at most options.captures of `all`, evenly spread.
std::vector<std::filesystem::path> adaptation_captures(const std::vector<std::filesystem::path>& all,
                                                       const AdaptationOptions& options);

// Adapts `generator` in place to the captures' planes (each {4,rows,cols}, as load_capture makes
// them) by (1); `measure` holds the camera's calibration. Call before prepare_inference.
AdaptationReport adapt_to_captures(Generator& generator, const std::vector<torch::Tensor>& planes,
                                   const DataConsistency& measure, const AdaptationOptions& options);

}  // namespace flatnet
