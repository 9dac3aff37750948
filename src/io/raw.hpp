#pragma once
// Raw FlatCam frames <-> measurement planes, as FlatNet's loader (demosaic_raw) does it:
// 16-bit PNG / 65535 -> Bayer planes b=[0::2,0::2] gb=[0::2,1::2] gr=[1::2,0::2] r=[1::2,1::2]
// -> hot pixels repaired -> optional small rotation -> crop -> double centring.
#include <array>
#include <filesystem>
#include <string>

#include <torch/torch.h>

#include "io/camera_config.hpp"

namespace flatnet {

// One preprocessed capture: the four measurement planes the calibration refers to.
struct Capture {
  torch::Tensor planes;  // {4, crop_h, crop_w} float32, order b, gb, gr, r
  std::string name;      // file name it came from (for outputs with the same name)
};

// {H,W} raw frame (any numeric type) -> {4, H/2, W/2} planes in b, gb, gr, r order.
torch::Tensor bayer_split(const torch::Tensor& raw);
// A raw frame's pixel (row, col) as {plane, row, col} of bayer_split's planes, and back.
inline std::array<int64_t, 3> plane_pixel(int64_t raw_row, int64_t raw_col) {
  return {(raw_row % 2) * 2 + raw_col % 2, raw_row / 2, raw_col / 2};
}
inline std::array<int64_t, 2> raw_pixel(int64_t plane, int64_t row, int64_t col) {
  return {2 * row + plane / 2, 2 * col + plane % 2};
}
// {4, H/2, W/2} -> {H,W}: the inverse of bayer_split.
torch::Tensor bayer_merge(const torch::Tensor& planes);

// Rotates each plane of {C,H,W} by `angle` radians with bilinear interpolation and zero fill,
// exactly as skimage.transform.warp(img, SimilarityTransform(rotation=angle)) (FlatNet's loader):
// output pixel (r, c) samples input (sin*c + cos*r, cos*c - sin*r).
torch::Tensor rotate_planes(const torch::Tensor& planes, double angle);

// Each listed raw pixel ({row, col} of the frame) in planes {4, H/2, W/2} replaced by the mean of
// its 8 same-colour neighbours that are not listed themselves (left as it is when all 8 are).
torch::Tensor repair_hot_pixels(const torch::Tensor& planes, const std::vector<std::array<int64_t, 2>>& hot_pixels);

// Y - rowmean - colmean + mean, per plane (Centring::plane) or with FlatNet's all-plane mean;
// Centring::level adds each plane's mean once more, so the planes carry their light level as DC.
torch::Tensor double_centre(const torch::Tensor& planes, Centring mode);
// Planes preprocessed with `mode` -> the centred planes the separable model describes (drops the
// DC of Centring::level; other modes unchanged). Tikhonov, TV and calibration read these.
torch::Tensor without_level(const torch::Tensor& planes, Centring mode);

// Full-scale raw frame ({H,W}, values in [0,1]) -> the window's planes {4, crop_h, crop_w} before
// centring (hot pixels repaired, then rotated and cropped): the light each pixel read (the camera fit's noise model
// needs it).
torch::Tensor raw_window(const torch::Tensor& raw_unit, const RawGeometry& g);
// raw_window's two halves: the Bayer planes {4,H/2,W/2} with the listed hot pixels repaired, and
// those planes rotated by the geometry's angle and cropped (a rotation search decodes once).
torch::Tensor repaired_planes(const torch::Tensor& raw_unit, const RawGeometry& g);
torch::Tensor rotated_window(const torch::Tensor& planes, const RawGeometry& g);
// Full-scale raw frame ({H,W}, values in [0,1]) -> measurement planes {4, crop_h, crop_w}.
torch::Tensor preprocess_raw(const torch::Tensor& raw_unit, const RawGeometry& g);

// A raw capture's header against the geometry (one channel, 16 bits, the raw frame's size), nothing
// decoded: commands check every capture so before they build anything the camera's size sets.
void check_raw_header(const std::filesystem::path& path, const RawGeometry& g);

// Reads a raw PNG, checks size and bit depth against the geometry, and preprocesses it.
Capture load_capture(const std::filesystem::path& path, const RawGeometry& g);
// load_capture's planes without the light level's DC: what Tikhonov, TV and calibration read.
torch::Tensor load_centred_planes(const std::filesystem::path& path, const RawGeometry& g);
// Reads a raw PNG as {H,W} float32 in [0,1] (codes / 65535), checking it against the geometry.
torch::Tensor load_raw_unit(const std::filesystem::path& path, const RawGeometry& g);

// ADC codes {H,W} (0 .. 2^adc_bits-1) -> stored 16-bit values (bits shifted to the top).
torch::Tensor adc_to_stored(const torch::Tensor& codes, int adc_bits);
// Camera codes {H,W} -> raw frame in [0,1] as a stored capture would read back (codes_to_stored / 65535).
torch::Tensor codes_to_unit(const torch::Tensor& codes, int bits);

}  // namespace flatnet
