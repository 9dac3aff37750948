#pragma once
// The reference camera built from any separable code pair (models/camera/README.md, "Building this
// camera from any separable code pair"): the mask (1 + u v^T) / 2 over the same sensor, with the
// same sub-pixel sampling, diffraction blur, vignetting and gains. With the MLS code for both axes
// it is rig.mat. Everything is a differentiable function of the codes (index gathers, a blur
// convolution, products), so a mask trainer can learn u and v through it.
#include <array>
#include <cstdint>

#include <torch/torch.h>

#include "optics/camera.hpp"

namespace flatnet {

struct SeparableCameraOptions {
  int64_t scene = 256;  // N: scene pixels per side
  int64_t plane_rows = 512, plane_cols = 640;
  double pixels_per_feature = 20.0 / 10.6;                   // R: sensor-plane pixels per mask feature
  int subsamples = 16;                                       // sub-positions per pixel
  double offset_rows = 0.3, offset_cols = 137.6;             // shadow offset, in features
  std::array<double, 4> blur_sigma{0.70, 0.85, 0.85, 1.00};  // b, gb, gr, r; plane pixels, along the sensor axis
  double vignette_rows = 0.25, vignette_cols = 0.2;          // 1 / (1 + f x^2)^2
  std::array<double, 4> channel_gain{0.85, 1.00, 1.00, 0.90};
  double full_well = 40000, read_noise = 4, dark = 0.02;
  int adc_bits = 10;
};

// One axis: the {rows, N} matrix whose entry (i, j) is the mean of code[floor(s) mod K] over the
// pixel's sub-positions t = (16 i + k + 0.5) / 16 / R, s = t + (N - 1 - j) + offset (no blur or
// vignette). `code` {K} in [-1, 1]; the result keeps its autograd graph.
torch::Tensor code_matrix(const torch::Tensor& code, int64_t rows, int64_t scene, double offset,
                          double pixels_per_feature, int subsamples);

// A Gaussian blur along dim 0 with scipy.ndimage.gaussian_filter1d's kernel (radius
// int(4 sigma + 0.5)) and edges extended with the nearest value. {rows, N} -> {rows, N}.
torch::Tensor blur_rows(const torch::Tensor& m, double sigma);

// The rig of the code pair u (rows) and v (columns), each {K} in [-1, 1] (float64 for an exact
// rig.mat; any float type keeps gradients).
Rig separable_rig(const torch::Tensor& u, const torch::Tensor& v, const SeparableCameraOptions& options = {});

// What a calibration of that rig measures: the centred window C_h sqrt(gain_c) PhiL_c[window rows]
// (and likewise Q), plus i.i.d. Gaussian error of `relative_error` (Frobenius, per matrix; the
// shipped calib.mat has 3 %), seeded.
Calibration calibration_of(const Rig& rig, const std::array<int64_t, 4>& crop, double relative_error, uint64_t seed);

// The mask (1 + u v^T) / 2's mean transmittance (1 + mean(u) mean(v)) / 2, differentiable.
torch::Tensor code_throughput(const torch::Tensor& u, const torch::Tensor& v);
// The code trainers' throughput constraint: 100 relu(|throughput - target| - tolerance)^2, 0 in the band.
torch::Tensor throughput_penalty(const torch::Tensor& throughput, double target, double tolerance);
// sign(x) forward, identity backward (straight-through): binary codes that still learn.
torch::Tensor straight_through_sign(const torch::Tensor& x);

// A separable mask's code pair: the mask is (1 + rows cols^T) / 2.
struct CodePair {
  torch::Tensor rows, cols;   // {K} float64, values in [-1, 1]
  double throughput() const;  // mean transmittance (1 + mean(rows) mean(cols)) / 2
};
// Reads code_rows and code_cols (vectors) from a .mat; errors name the file and the variable
// (missing, not a vector, non-finite, values outside [-1, 1]).
CodePair load_code_pair(const std::filesystem::path& path);

// code_rows and code_cols as float64 columns (what load_code_pair reads), atomically.
void save_code_pair(const std::filesystem::path& path, const torch::Tensor& rows, const torch::Tensor& cols);

// rig.mat's variables (PhiL_b.., PhiR_b.., gain_b.., vig_rows, vig_cols, full_well, read_noise, dark, adc_bits).
void save_rig(const std::filesystem::path& path, const Rig& rig);

// The camera a code pair makes, as files in `folder`: rig.mat, calib.mat (calibration_of with
// `calib_error` and `seed`, in `camera`'s crop) and camera.yaml (`camera`'s geometry named after the
// folder, under the comment line `comment`). `flatnet mask camera` and co-design runs write it.
void write_code_pair_camera(const std::filesystem::path& folder, const CodePair& codes, CameraConfig camera,
                            double calib_error, uint64_t seed, const std::string& comment,
                            const SeparableCameraOptions& options = {});

}  // namespace flatnet
