#include "eval/metrics.hpp"

#include <opencv2/imgproc.hpp>

#include "io/image.hpp"

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
