#pragma once
// Image quality metrics on RGB images in [0,1] (data range 1).
#include <filesystem>
#include <string>
#include <vector>

#include <torch/torch.h>

namespace flatnet {

// PSNR over all pixels and channels of {3,H,W} (or {B,3,H,W}, averaged per image).
double psnr(const torch::Tensor& a, const torch::Tensor& b);
// SSIM (Wang et al. 2004): Gaussian window sigma 1.5 (11x11), K1 = 0.01, K2 = 0.03, population
// covariances, border of 5 pixels excluded, mean over channels; equals
// skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
// use_sample_covariance=False, data_range=1, channel_axis=2).
double ssim(const torch::Tensor& a, const torch::Tensor& b);

// Colourfulness of an sRGB {3,H,W} image in [0,1] (Hasler & Suesstrunk 2003, eq. 3):
// sqrt(sd(rg)^2 + sd(yb)^2) + 0.3 sqrt(mean(rg)^2 + mean(yb)^2), rg = R - G, yb = (R + G) / 2 - B,
// on the 0..1 scale (the paper's 0..255 values are 255 times these). 0 for a grey image.
double colourfulness(const torch::Tensor& rgb);
// Detail: the mean Sobel gradient magnitude of the luma (0.299 R + 0.587 G + 0.114 B), over the
// pixels whose 3x3 neighbourhood lies inside the image. 0 for a flat image.
double luma_detail(const torch::Tensor& rgb);
// Stripe energy of an output against its truth, both {3,H,W} in [0,1], in 8-bit codes: the error
// image's row means and column means (per channel), each less its smooth trend (a centred moving
// average over 15 samples, the window shrinking at the ends), as one RMS over both profiles and the
// channels, times 255. Stripes along rows or columns (an inversion's periodic artefacts) stand out in
// those profiles; a constant or slowly varying error, and noise that averages out along a row, do
// not. 0 for a perfect output.
double stripe_energy(const torch::Tensor& output, const torch::Tensor& truth);

// Contact sheet: one row per image, ground truth then each method; labels above the columns.
// images[row][col] are {3,H,W} in [0,1]. Written as an 8-bit PNG.
void write_contact_sheet(const std::filesystem::path& path, const std::vector<std::string>& column_labels,
                         const std::vector<std::string>& row_labels,
                         const std::vector<std::vector<torch::Tensor>>& images);

}  // namespace flatnet
