#include "eval/metrics.hpp"

#include <opencv2/imgproc.hpp>

#include "io/image.hpp"
#include "nn/losses.hpp"

namespace flatnet {

double psnr(const torch::Tensor& a, const torch::Tensor& b) {
  TORCH_CHECK(a.sizes() == b.sizes(), "psnr: shapes differ ", a.sizes(), " vs ", b.sizes());
  auto mse = (a.to(torch::kFloat64) - b.to(torch::kFloat64)).pow(2).mean().item<double>();
  return 10.0 * std::log10(1.0 / std::max(mse, 1e-20));
}

double ssim(const torch::Tensor& a, const torch::Tensor& b) {
  TORCH_CHECK(a.sizes() == b.sizes() && a.dim() == 3, "ssim: expects equal {C,H,W}");
  const double sigma = 1.5;
  const int radius = 5;  // skimage: int(3.5 * sigma + 0.5) = 5 -> 11x11 window
  auto k = torch::arange(-radius, radius + 1, torch::kFloat64);
  k = torch::exp(-0.5 * (k / sigma).pow(2));
  k = k / k.sum();
  auto x = a.to(torch::kFloat64).unsqueeze(1), y = b.to(torch::kFloat64).unsqueeze(1);  // {C,1,H,W}
  auto filt = [&](const torch::Tensor& t) {  // separable Gaussian, 'valid' = skimage's cropped border
    auto r = torch::conv2d(t, k.view({1, 1, 1, -1}));
    return torch::conv2d(r, k.view({1, 1, -1, 1}));
  };
  auto ux = filt(x), uy = filt(y);
  auto vx = filt(x * x) - ux * ux, vy = filt(y * y) - uy * uy, vxy = filt(x * y) - ux * uy;
  const double C1 = 0.01 * 0.01, C2 = 0.03 * 0.03;
  auto s = ((2 * ux * uy + C1) * (2 * vxy + C2)) / ((ux * ux + uy * uy + C1) * (vx + vy + C2));
  return s.mean({1, 2, 3}).mean().item<double>();
}

double colourfulness(const torch::Tensor& rgb) {
  TORCH_CHECK(rgb.dim() == 3 && rgb.size(0) == 3, "colourfulness: expects {3,H,W}, got ", rgb.sizes());
  const auto x = rgb.to(torch::kFloat64);
  const auto r = x[0], g = x[1], b = x[2];
  const auto rg = r - g, yb = 0.5 * (r + g) - b;
  const double sd = std::sqrt(rg.var(false).item<double>() + yb.var(false).item<double>());
  const double mean = std::hypot(rg.mean().item<double>(), yb.mean().item<double>());
  return sd + 0.3 * mean;
}

double luma_detail(const torch::Tensor& rgb) {
  TORCH_CHECK(rgb.dim() == 3 && rgb.size(0) == 3 && rgb.size(1) >= 3 && rgb.size(2) >= 3,
              "detail: expects {3,H,W} of at least 3x3, got ", rgb.sizes());
  const auto x = rgb.to(torch::kFloat64);
  const auto luma = (0.299 * x[0] + 0.587 * x[1] + 0.114 * x[2]).view({1, 1, x.size(1), x.size(2)});
  const auto sobel_x =
      torch::tensor({-1.0, 0.0, 1.0, -2.0, 0.0, 2.0, -1.0, 0.0, 1.0}, torch::kFloat64).view({1, 1, 3, 3});
  const auto gx = torch::conv2d(luma, sobel_x), gy = torch::conv2d(luma, sobel_x.transpose(2, 3));
  return (gx * gx + gy * gy).sqrt().mean().item<double>();
}

double stripe_energy(const torch::Tensor& output, const torch::Tensor& truth) {
  TORCH_CHECK(output.dim() == 3 && output.size(0) == 3 && output.sizes() == truth.sizes(),
              "stripe energy: expects two {3,H,W} images of one size, got ", output.sizes(), " and ", truth.sizes());
  // The training term's profiles (nn/losses.hpp), in float64.
  const auto squares = stripe_loss(output.to(torch::kFloat64).unsqueeze(0), truth.to(torch::kFloat64).unsqueeze(0));
  return 255.0 * std::sqrt(squares.item<double>());
}

void write_contact_sheet(const std::filesystem::path& path, const std::vector<std::string>& column_labels,
                         const std::vector<std::string>& row_labels,
                         const std::vector<std::vector<torch::Tensor>>& images) {
  const int64_t tile = 256, gap = 4, header = 28, margin = 0;
  const int64_t cols = static_cast<int64_t>(column_labels.size()), rows = static_cast<int64_t>(images.size());
  const int64_t W = cols * (tile + gap) + gap, H = header + rows * (tile + gap) + gap + margin;
  auto sheet = torch::full({3, H, W}, 1.0f);
  for (int64_t r = 0; r < rows; ++r)
    for (int64_t c = 0; c < cols && c < static_cast<int64_t>(images[r].size()); ++c) {
      auto img = resize(images[r][c].to(torch::kFloat32), tile, tile);
      const int64_t y0 = header + r * (tile + gap) + gap, x0 = c * (tile + gap) + gap;
      sheet.slice(1, y0, y0 + tile).slice(2, x0, x0 + tile).copy_(img);
    }
  // Labels drawn with OpenCV on an 8-bit copy.
  auto hwc = (sheet * 255).round().to(torch::kUInt8).permute({1, 2, 0}).contiguous();
  cv::Mat m(static_cast<int>(H), static_cast<int>(W), CV_8UC3, hwc.data_ptr<uint8_t>());
  for (int64_t c = 0; c < cols; ++c)
    cv::putText(m, column_labels[c], cv::Point(static_cast<int>(c * (tile + gap) + gap + 4), 20),
                cv::FONT_HERSHEY_SIMPLEX, 0.55, cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
  for (int64_t r = 0; r < rows && r < static_cast<int64_t>(row_labels.size()); ++r)
    cv::putText(m, row_labels[r].substr(0, 30),
                cv::Point(gap + 4, static_cast<int>(header + r * (tile + gap) + tile - 6)), cv::FONT_HERSHEY_SIMPLEX,
                0.4, cv::Scalar(255, 255, 0), 1, cv::LINE_AA);
  auto out = torch::from_blob(m.data, {H, W, 3}, torch::kUInt8).permute({2, 0, 1}).to(torch::kFloat32) / 255.0f;
  write_rgb8(path, out);
}

}  // namespace flatnet
