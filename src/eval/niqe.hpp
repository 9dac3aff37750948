#pragma once
// NIQE, the Natural Image Quality Evaluator (Mittal, Soundararajan and Bovik, IEEE SPL 2013): a
// no-reference score, lower is more natural. Features of natural-scene statistics on patches are
// modelled by a multivariate Gaussian (MVG), fitted once on pristine photographs; an image's score
// is the distance between that model and the MVG of its own patches' features.
//
// Per patch and scale (the image, then the image at half size), 18 features of the MSCN
// coefficients  I^ = (I - mu) / (sigma + 1)  (mu, sigma: 7x7 Gaussian-weighted local mean and
// deviation, sigma 7/6, on grey levels 0..255):
//   - the generalised Gaussian fit of I^ (shape alpha, variance),
//   - for the products of I^ with its neighbour right, below, and on both diagonals, the
//     asymmetric generalised Gaussian fit (shape, mean, left and right variance).
// 36 features in all. Pristine patches are kept only when sharp: mean sigma above 0.75 of the
// image's sharpest patch. Score = sqrt((mu_p - mu_d)^T pinv((S_p + S_d) / 2) (mu_p - mu_d)).
//
// The paper's patches are 96 pixels; flatnet's reconstructions are 256x256, which that leaves
// with four patches, so the default is 48 (25 patches); the patch size is part of the model file.
#include <filesystem>
#include <functional>
#include <vector>

#include <torch/torch.h>

namespace flatnet {

struct NiqeModel {
  int64_t patch = 48;                 // patch side at full scale (half at the second scale)
  double sharpness_threshold = 0.75;  // pristine patches kept: mean sigma > threshold x the sharpest
  torch::Tensor mean;                 // {36} float64: the pristine features' mean
  torch::Tensor cov;                  // {36,36} float64: their covariance
  int64_t images = 0, patches = 0;    // what the fit saw
};

// {3,H,W} or {1,H,W} in [0,1] -> {H,W} grey levels 0..255 (ITU-R BT.601 luma, as MATLAB's rgb2gray).
torch::Tensor niqe_gray(const torch::Tensor& image);

// {P,36} features of an image's patches (rows with a non-finite feature, e.g. a flat patch, are
// dropped). With `sharp_only` (fitting), only the sharp patches.
torch::Tensor niqe_features(const torch::Tensor& gray255, int64_t patch, bool sharp_only = false,
                            double sharpness_threshold = 0.75);

// Fits the pristine model on images (each through `load`, e.g. the display scene of a photograph).
NiqeModel fit_niqe(const std::vector<std::filesystem::path>& images,
                   const std::function<torch::Tensor(const std::filesystem::path&)>& load, int64_t patch = 48,
                   bool progress = true);

// The score of one image ({3,H,W} in [0,1]); NaN when it has fewer than two usable patches.
double niqe_score(const NiqeModel& model, const torch::Tensor& image);

// Model files: .mat with mu_prisparam {1,36}, cov_prisparam {36,36} (the names of the authors'
// modelparameters.mat), patch_size, sharpness_threshold, images, patches.
void save_niqe(const std::filesystem::path& path, const NiqeModel& model);
NiqeModel load_niqe(const std::filesystem::path& path);  // errors name the file and the variable

// Shape estimates by moment matching (the authors' estimateggdparam / estimateaggdparam):
// GGD -> {alpha, variance}; AGGD -> {alpha, mean, left variance, right variance}.
std::pair<double, double> fit_ggd(const std::vector<double>& x);
std::array<double, 4> fit_aggd(const std::vector<double>& x);

}  // namespace flatnet
