#pragma once
// Learning the separable FlatCam's codes end to end (issue: masks that make the FlatCam better).
// The Wiener-protocol trainer (mask_trainer) learns a mask for circular convolution; this one
// learns the code pair u (rows), v (columns) of the real, separable camera:
//   codes -> PhiL, PhiR (sub-pixel sampling, blur, vignette; optics/separable_camera)
//         -> capture with Poisson (Gaussian approximation) and read noise, the open-mask pedestal
//         -> the 500x620 window, double-centred
//         -> Tikhonov with the exact centred calibration, through the SVDs (eq. 2.6), learnable lambda
//         -> MSE against the linear-light scene.
// Throughput (1 + mean(u) mean(v)) / 2 is held within target +- tolerance by a penalty; the binary
// variant uses sign(u), sign(v) forward with a straight-through gradient (for fabrication).
#include <filesystem>
#include <string>

#include <torch/torch.h>

#include "train/loop.hpp"

namespace flatnet {

// The schedule (train/loop.hpp): 1,000 Adam steps of 8 at lr 0.02 (on the codes' pre-activations), a
// log row every 25, validation every 100; with train.minutes the run stops early, writing its codes.
struct SeparableTrainOptions : Schedule {
  SeparableTrainOptions() : Schedule{1000, 0, 8, 0.02, 0, 100, 25, true} {}
  std::filesystem::path images;  // photographs; the training side of simulate's split
  double val_fraction = 0.1;     // that split (flatnet simulate's defaults: the same photographs held out)
  uint64_t split_seed = 1;
  std::filesystem::path init_codes;  // .mat with code_rows, code_cols to start from (MLS); empty: random
  int64_t code_length = 511;         // elements per code when init_codes is empty
  int64_t train_limit = 400;         // photographs loaded for training (0: all)
  int64_t val_count = 32;            // held-out-split photographs for validation
  double lambda_init = 1e-4;         // Tikhonov regulariser (absolute, as recon's), learned as its log
  double target_throughput = 0.5, throughput_tolerance = 0.05;
  bool binary = false;
  std::filesystem::path out;  // codes.mat, lambda.txt, log.csv, curve.png, latest.ckpt
  // Continue the run in `out` from its latest.ckpt (written at every validation, at the end and
  // when stopped early): codes, lambda, Adam's moments, the step and the data and noise generator.
  bool resume = false;
  // With resume: continue a latest.ckpt of another run too (its run id differs from OUT/run_id.txt).
  bool force = false;
};

struct SeparableTrainSummary {
  double val_psnr_start = 0, val_psnr = 0, lambda = 0, throughput = 0, seconds = 0;
  int64_t steps = 0;
};

SeparableTrainSummary train_separable_codes(const SeparableTrainOptions& options);

// Validation PSNR (linear light, clamped to [0,1]) of a code pair with Tikhonov at `lambda`, on
// scenes {N,S,S} (sRGB luma in [0,1]) with the noise of `seed`.
double separable_psnr(const torch::Tensor& u, const torch::Tensor& v, double lambda, const torch::Tensor& scenes,
                      uint64_t seed);

}  // namespace flatnet
