#pragma once
// The fair evaluation of any FlatCam mask (FlatNet thesis, "learning the mask"): grayscale scenes
// captured through the mask's PSF under the same noise, Wiener deconvolution with gamma tuned on
// validation images, PSNR on held-out ones.
#include <filesystem>
#include <vector>

#include <torch/torch.h>

#include "optics/mask.hpp"

namespace flatnet {

// Photographs -> {N,size,size} luma (Rec. 601 weights on the sRGB values) in [0,1].
torch::Tensor load_luma_scenes(const std::vector<std::filesystem::path>& images, int64_t size, int workers);

// The sum over images of PSNR (reconstruction clamped to [0,1]), {B,N,N} against {B,N,N}.
double psnr_sum(const torch::Tensor& reconstruction, const torch::Tensor& truth);
// Mean PSNR (reconstruction clamped to [0,1]) over scenes, captured through `window` with noise
// drawn from `seed`, reconstructed by Wiener with `gamma`.
double mask_psnr(const torch::Tensor& window, double gamma, const torch::Tensor& scenes, const WienerCamera& cam,
                 uint64_t seed, int64_t batch = 8);
// The gamma (log grid, then refined) that maximises mask_psnr on `scenes`.
double tune_gamma(const torch::Tensor& window, const torch::Tensor& scenes, const WienerCamera& cam, uint64_t seed);

}  // namespace flatnet
