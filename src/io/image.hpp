#pragma once
// Image files through OpenImageIO, and the colour conversions the camera model needs.
#include <array>
#include <filesystem>
#include <vector>

#include <torch/torch.h>

namespace flatnet {

// Reads an 8- or 16-bit image as RGB in [0,1], {3,H,W} float32. Grey images are replicated to
// three channels, alpha is dropped.
torch::Tensor read_rgb(const std::filesystem::path& path);

// Reads a single-channel 16-bit image exactly, {H,W} int32 holding the stored 0..65535 codes.
// Errors name the file and the problem (channels, bit depth).
torch::Tensor read_gray16(const std::filesystem::path& path);

// An image's size and sample format from its header, nothing decoded: what a reader checks before
// it allocates for the image (the size a file claims is data, not a promise).
struct ImageHeader {
  int64_t width = 0, height = 0;
  int channels = 0;
  int bits = 0;  // per sample (8, 16, 32)
};
ImageHeader read_image_header(const std::filesystem::path& path);

// Writes {3,H,W} values in [0,1] (clamped) as an 8-bit RGB image, atomically.
void write_rgb8(const std::filesystem::path& path, const torch::Tensor& rgb);
// Writes {H,W} codes 0..65535 as a 16-bit single-channel image, atomically.
void write_gray16(const std::filesystem::path& path, const torch::Tensor& codes);

// Resizes {C,H,W} to {C,h,w} ignoring aspect ratio (area averaging when shrinking, as an
// anti-aliased resize does; bilinear when enlarging).
torch::Tensor resize(const torch::Tensor& chw, int64_t h, int64_t w);

// Standard sRGB transfer functions (IEC 61966-2-1), elementwise.
torch::Tensor srgb_to_linear(const torch::Tensor& x);
torch::Tensor linear_to_srgb(const torch::Tensor& x);
// A display value -> light in a calibration's scene units, and back (CameraConfig::display_gamma):
// the power x^gamma, or the sRGB curves above when gamma is 0. light_to_display clamps to [0, 1].
torch::Tensor display_to_light(const torch::Tensor& x, double gamma);
torch::Tensor light_to_display(const torch::Tensor& x, double gamma);

// Per-channel reconstruction planes {.., 4, H, W} in FlatNet's order (b, gb, gr, r), linear light
// -> RGB {.., 3, H, W}: R from r, G the mean of gb and gr, B from b.
torch::Tensor bayer_planes_to_rgb(const torch::Tensor& planes);
// Planes {..,4,H,W} (b, gb, gr, r) each of which sees a mix of the display's primaries, mix {4,3}
// (rows b, gb, gr, r; columns R, G, B; CameraConfig::colour_mix) -> RGB {..,3,H,W}: the primaries
// that explain the four planes best (least squares, the mix's pseudo-inverse).
torch::Tensor unmix_primaries(const torch::Tensor& planes, const torch::Tensor& mix);
// A camera file's colour_mix rows <-> the mix {4,3} float64.
torch::Tensor colour_mix_matrix(const std::vector<std::array<double, 3>>& rows);
std::vector<std::array<double, 3>> colour_mix_rows(const torch::Tensor& mix);
// Linear-light planes {..,4,N,N} (b, gb, gr, r) -> sRGB image {..,3,N,N} in [0,1].
torch::Tensor planes_to_srgb(const torch::Tensor& planes);
// RGB {.., 3, H, W} -> planes {.., 4, H, W}: b = B, gb = gr = G, r = R.
torch::Tensor rgb_to_bayer_planes(const torch::Tensor& rgb);

}  // namespace flatnet
