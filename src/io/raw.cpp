#include "io/raw.hpp"

#include <unordered_set>

#include "core/error.hpp"
#include "io/image.hpp"

namespace flatnet {

using torch::indexing::None;
using torch::indexing::Slice;

torch::Tensor bayer_split(const torch::Tensor& raw) {
  TORCH_CHECK(raw.dim() == 2 && raw.size(0) % 2 == 0 && raw.size(1) % 2 == 0, "bayer_split expects even {H,W}");
  return torch::stack({raw.index({Slice(0, None, 2), Slice(0, None, 2)}),    // b
                       raw.index({Slice(0, None, 2), Slice(1, None, 2)}),    // gb
                       raw.index({Slice(1, None, 2), Slice(0, None, 2)}),    // gr
                       raw.index({Slice(1, None, 2), Slice(1, None, 2)})});  // r
}

torch::Tensor bayer_merge(const torch::Tensor& planes) {
  TORCH_CHECK(planes.dim() == 3 && planes.size(0) == 4, "bayer_merge expects {4,h,w}");
  const auto h = planes.size(1), w = planes.size(2);
  auto raw = torch::empty({2 * h, 2 * w}, planes.options());
  raw.index_put_({Slice(0, None, 2), Slice(0, None, 2)}, planes[0]);
  raw.index_put_({Slice(0, None, 2), Slice(1, None, 2)}, planes[1]);
  raw.index_put_({Slice(1, None, 2), Slice(0, None, 2)}, planes[2]);
  raw.index_put_({Slice(1, None, 2), Slice(1, None, 2)}, planes[3]);
  return raw;
}

torch::Tensor rotate_planes(const torch::Tensor& planes, double angle) {
  if (angle == 0.0) return planes;
  const auto H = planes.size(-2), W = planes.size(-1);
  auto opts = torch::TensorOptions().dtype(torch::kFloat64);
  auto r = torch::arange(H, opts).unsqueeze(1).expand({H, W});
  auto c = torch::arange(W, opts).unsqueeze(0).expand({H, W});
  const double cs = std::cos(angle), sn = std::sin(angle);
  auto src_r = sn * c + cs * r;  // inverse map of the similarity transform (skimage: x=col, y=row)
  auto src_c = cs * c - sn * r;
  auto r0 = torch::floor(src_r), c0 = torch::floor(src_c);
  auto fr = (src_r - r0).to(planes.scalar_type()), fc = (src_c - c0).to(planes.scalar_type());
  auto flat = planes.reshape({-1, H * W});
  // Bilinear interpolation; neighbours outside the image contribute zero (cval = 0).
  auto sample = [&](const torch::Tensor& rr, const torch::Tensor& cc) {
    auto valid = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W);
    auto idx = (rr.clamp(0, H - 1) * W + cc.clamp(0, W - 1)).to(torch::kLong).reshape({-1});
    auto v = flat.index_select(1, idx).reshape(planes.sizes());
    return v * valid.to(planes.scalar_type());
  };
  auto out = sample(r0, c0) * (1 - fr) * (1 - fc) + sample(r0, c0 + 1) * (1 - fr) * fc +
             sample(r0 + 1, c0) * fr * (1 - fc) + sample(r0 + 1, c0 + 1) * fr * fc;
  return out;
}

torch::Tensor repair_hot_pixels(const torch::Tensor& planes, const std::vector<std::array<int64_t, 2>>& hot_pixels) {
  if (hot_pixels.empty()) return planes;
  TORCH_CHECK(planes.dim() == 3 && planes.size(0) == 4, "repair_hot_pixels expects planes {4,h,w}");
  const int64_t H = planes.size(1), W = planes.size(2);
  std::unordered_set<int64_t> listed;  // flat indices into the planes
  for (const auto& [raw_row, raw_col] : hot_pixels) {
    const auto [plane, row, col] = plane_pixel(raw_row, raw_col);
    if (raw_row >= 0 && raw_col >= 0 && row < H && col < W) listed.insert((plane * H + row) * W + col);
  }
  auto out = planes.contiguous().clone();
  // Only the listed pixels are visited (a few hundred), each from the unrepaired neighbours.
  AT_DISPATCH_FLOATING_TYPES(out.scalar_type(), "repair_hot_pixels", [&] {
    auto* v = out.data_ptr<scalar_t>();
    std::vector<std::pair<int64_t, scalar_t>> repaired;
    for (const int64_t i : listed) {
      const int64_t plane = i / (H * W), r = i / W % H, c = i % W;
      double sum = 0;
      int count = 0;
      for (int64_t dr = -1; dr <= 1; ++dr)
        for (int64_t dc = -1; dc <= 1; ++dc) {
          const int64_t rr = r + dr, cc = c + dc;
          if ((dr == 0 && dc == 0) || rr < 0 || rr >= H || cc < 0 || cc >= W) continue;
          const int64_t j = plane * H * W + rr * W + cc;
          if (listed.count(j)) continue;
          sum += static_cast<double>(v[j]);
          ++count;
        }
      if (count > 0) repaired.emplace_back(i, static_cast<scalar_t>(sum / count));
    }
    for (const auto& [i, value] : repaired) v[i] = value;
  });
  return out;
}

torch::Tensor double_centre(const torch::Tensor& planes, Centring mode) {
  if (mode == Centring::none) return planes;
  auto row_means = planes.mean(-1, true);                                            // {..,C,H,1}
  auto col_means = planes.mean(-2, true);                                            // {..,C,1,W}
  const auto plane_mean = planes.mean({-2, -1}, true);                               // {..,C,1,1}
  const auto all_mean = mode == Centring::flatnet ? planes.mean({-3, -2, -1}, true)  // FlatNet: rowMeans.mean()
                                                  : plane_mean;
  const auto centred = planes - row_means - col_means + all_mean;  // plane: zero mean per plane
  return mode == Centring::level ? centred + plane_mean : centred;
}

torch::Tensor without_level(const torch::Tensor& planes, Centring mode) {
  return mode == Centring::level ? planes - planes.mean({-2, -1}, true) : planes;
}

torch::Tensor repaired_planes(const torch::Tensor& raw_unit, const RawGeometry& g) {
  return repair_hot_pixels(bayer_split(raw_unit.to(torch::kFloat32)), g.hot_pixels);  // {4,512,640}
}

torch::Tensor rotated_window(const torch::Tensor& planes, const RawGeometry& g) {
  return rotate_planes(planes, g.rotation)
      .index({Slice(), Slice(g.crop[0], g.crop[0] + g.crop[2]), Slice(g.crop[1], g.crop[1] + g.crop[3])});
}

torch::Tensor raw_window(const torch::Tensor& raw_unit, const RawGeometry& g) {
  return rotated_window(repaired_planes(raw_unit, g), g);
}

torch::Tensor preprocess_raw(const torch::Tensor& raw_unit, const RawGeometry& g) {
  return double_centre(raw_window(raw_unit, g), g.centring).contiguous();  // {4,500,620}
}

namespace {

void require_raw_size(const std::filesystem::path& path, int64_t height, int64_t width, const RawGeometry& g) {
  require(height == g.raw_height && width == g.raw_width, path,
          "raw capture is " + std::to_string(width) + "x" + std::to_string(height) + " (WxH), this camera gives " +
              std::to_string(g.raw_width) + "x" + std::to_string(g.raw_height));
}

}  // namespace

void check_raw_header(const std::filesystem::path& path, const RawGeometry& g) {
  const auto h = read_image_header(path);
  require(h.channels == 1, path,
          "raw capture must be single-channel (Bayer mosaic), found " + std::to_string(h.channels) + " channels");
  require(h.bits == 16, path, "raw capture must be 16-bit, found " + std::to_string(h.bits) + "-bit samples");
  require_raw_size(path, h.height, h.width, g);
}

torch::Tensor load_raw_unit(const std::filesystem::path& path, const RawGeometry& g) {
  auto codes = read_gray16(path);
  require_raw_size(path, codes.size(0), codes.size(1), g);
  return codes.to(torch::kFloat32) / 65535.0f;
}

Capture load_capture(const std::filesystem::path& path, const RawGeometry& g) {
  return {preprocess_raw(load_raw_unit(path, g), g), path.filename().string()};
}

torch::Tensor load_centred_planes(const std::filesystem::path& path, const RawGeometry& g) {
  return without_level(load_capture(path, g).planes, g.centring);
}

torch::Tensor adc_to_stored(const torch::Tensor& codes, int adc_bits) {
  return codes.to(torch::kInt32) * (1 << (16 - adc_bits));
}

torch::Tensor codes_to_unit(const torch::Tensor& codes, int bits) {
  return (codes.to(torch::kFloat32) * static_cast<float>(1 << (16 - bits))).clamp_max(65535.0f) / 65535.0f;
}

}  // namespace flatnet
