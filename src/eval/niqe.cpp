#include "eval/niqe.hpp"

#include <array>
#include <cmath>
#include <thread>

#include <opencv2/imgproc.hpp>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/mat.hpp"

namespace flatnet {

namespace {

constexpr int kFeatures = 36;

// Shape grid 0.2:0.001:10 with, per shape a, the generalised Gaussian's moment ratios
//   ggd(a)  = G(1/a) G(3/a) / G(2/a)^2      (E[x^2] / E[|x|]^2)
//   aggd(a) = G(2/a)^2 / (G(1/a) G(3/a))   (its inverse)
struct ShapeTable {
  std::vector<double> shape, ggd, aggd;
  ShapeTable() {
    for (int i = 0; i <= 9800; ++i) {
      const double a = 0.2 + 0.001 * i;
      const double r = std::exp(std::lgamma(1 / a) + std::lgamma(3 / a) - 2 * std::lgamma(2 / a));
      shape.push_back(a);
      ggd.push_back(r);
      aggd.push_back(1 / r);
    }
  }
};
const ShapeTable& shapes() {
  static const ShapeTable table;
  return table;
}

// The index of the value nearest to target in a monotonic table (both ratios are monotonic in the
// shape), by bisection: the same answer as the authors' exhaustive min(|r - target|).
size_t nearest(const std::vector<double>& values, double target) {
  const bool increasing = values.front() < values.back();
  size_t lo = 0, hi = values.size() - 1;
  while (hi - lo > 1) {
    const size_t mid = (lo + hi) / 2;
    if ((values[mid] < target) == increasing)
      lo = mid;
    else
      hi = mid;
  }
  return std::abs(values[lo] - target) <= std::abs(values[hi] - target) ? lo : hi;
}

cv::Mat to_mat(const torch::Tensor& gray) {  // {H,W} -> CV_64F (a copy)
  const auto g = gray.to(torch::kFloat64).contiguous();
  return cv::Mat(static_cast<int>(g.size(0)), static_cast<int>(g.size(1)), CV_64F, g.data_ptr<double>()).clone();
}

// MSCN coefficients and the local deviation sigma (7x7 Gaussian window, sigma 7/6, replicated borders).
std::pair<cv::Mat, cv::Mat> mscn(const cv::Mat& image) {
  const cv::Mat k = cv::getGaussianKernel(7, 7.0 / 6.0, CV_64F);
  cv::Mat mu, mu_sq, sigma;
  cv::sepFilter2D(image, mu, CV_64F, k, k, cv::Point(-1, -1), 0, cv::BORDER_REPLICATE);
  cv::sepFilter2D(image.mul(image), mu_sq, CV_64F, k, k, cv::Point(-1, -1), 0, cv::BORDER_REPLICATE);
  sigma = cv::abs(mu_sq - mu.mul(mu));
  cv::sqrt(sigma, sigma);
  cv::Mat structure = (image - mu) / (sigma + 1.0);
  return {structure, sigma};
}

// The 18 features of one MSCN patch: GGD of the coefficients, AGGD of the four neighbour
// products (neighbours taken cyclically within the patch, as MATLAB's circshift).
std::array<double, 18> patch_features(const cv::Mat& p) {
  std::array<double, 18> f{};
  std::vector<double> values(p.begin<double>(), p.end<double>());
  const auto [alpha, variance] = fit_ggd(values);
  f[0] = alpha;
  f[1] = variance;
  const int rows = p.rows, cols = p.cols;
  const int shifts[4][2] = {{0, 1}, {1, 0}, {1, 1}, {1, -1}};
  std::vector<double> pair(values.size());
  for (int s = 0; s < 4; ++s) {
    for (int r = 0; r < rows; ++r)
      for (int c = 0; c < cols; ++c) {
        // circshift(x, [dr dc]) puts x(r - dr, c - dc) at (r, c)
        const int rr = (r - shifts[s][0] + rows) % rows, cc = (c - shifts[s][1] + cols) % cols;
        pair[static_cast<size_t>(r) * cols + c] = p.at<double>(r, c) * p.at<double>(rr, cc);
      }
    const auto a = fit_aggd(pair);
    for (int j = 0; j < 4; ++j) f[2 + 4 * s + j] = a[j];
  }
  return f;
}

// Mean and unbiased covariance of the rows of {N,D} (float64).
std::pair<torch::Tensor, torch::Tensor> mean_and_cov(const torch::Tensor& x) {
  const auto mean = x.mean(0);
  const auto centred = x - mean;
  return {mean, centred.t().matmul(centred) / std::max<int64_t>(1, x.size(0) - 1)};
}

}  // namespace

std::pair<double, double> fit_ggd(const std::vector<double>& x) {
  double sum_sq = 0, sum_abs = 0;
  for (double v : x) sum_sq += v * v, sum_abs += std::abs(v);
  const double variance = sum_sq / x.size(), mean_abs = sum_abs / x.size();
  if (!(mean_abs > 0)) return {std::nan(""), variance};
  const auto& t = shapes();
  return {t.shape[nearest(t.ggd, variance / (mean_abs * mean_abs))], variance};
}

std::array<double, 4> fit_aggd(const std::vector<double>& x) {
  double left = 0, right = 0, sum_abs = 0, sum_sq = 0;
  int64_t n_left = 0, n_right = 0;
  for (double v : x) {
    if (v < 0) left += v * v, ++n_left;
    if (v > 0) right += v * v, ++n_right;
    sum_abs += std::abs(v), sum_sq += v * v;
  }
  const double nan = std::nan("");
  if (n_left == 0 || n_right == 0 || !(sum_sq > 0)) return {nan, nan, nan, nan};
  const double left_sd = std::sqrt(left / n_left), right_sd = std::sqrt(right / n_right);
  const double g = left_sd / right_sd;
  const double r = (sum_abs / x.size()) * (sum_abs / x.size()) / (sum_sq / x.size());
  const double r_norm = r * (g * g * g + 1) * (g + 1) / ((g * g + 1) * (g * g + 1));
  const auto& t = shapes();
  const double alpha = t.shape[nearest(t.aggd, r_norm)];
  const double mean = (right_sd - left_sd) * std::exp(std::lgamma(2 / alpha) - std::lgamma(1 / alpha)) *
                      std::sqrt(std::exp(std::lgamma(1 / alpha) - std::lgamma(3 / alpha)));
  return {alpha, mean, left_sd * left_sd, right_sd * right_sd};
}

torch::Tensor niqe_gray(const torch::Tensor& image) {
  TORCH_CHECK(image.dim() == 3 && (image.size(0) == 3 || image.size(0) == 1), "niqe: {3,H,W} or {1,H,W} expected, got ",
              image.sizes());
  const auto x = image.to(torch::kFloat64);
  if (x.size(0) == 1) return x[0] * 255.0;
  return (0.2989 * x[0] + 0.5870 * x[1] + 0.1140 * x[2]) * 255.0;
}

torch::Tensor niqe_features(const torch::Tensor& gray255, int64_t patch, bool sharp_only, double sharpness_threshold) {
  TORCH_CHECK(patch >= 8 && patch % 2 == 0, "niqe: the patch size must be even and at least 8");
  cv::Mat image = to_mat(gray255);
  const int nr = image.rows / static_cast<int>(patch), nc = image.cols / static_cast<int>(patch);
  if (nr == 0 || nc == 0) return torch::empty({0, kFeatures}, torch::kFloat64);
  image = image(cv::Rect(0, 0, nc * static_cast<int>(patch), nr * static_cast<int>(patch))).clone();
  auto features = torch::empty({nr * nc, kFeatures}, torch::kFloat64);
  auto f = features.accessor<double, 2>();
  std::vector<double> sharpness(static_cast<size_t>(nr) * nc);
  for (int scale = 0; scale < 2; ++scale) {
    const int side = static_cast<int>(patch) >> scale;
    const auto [structure, sigma] = mscn(image);
    for (int i = 0; i < nr; ++i)
      for (int j = 0; j < nc; ++j) {
        const cv::Rect box(j * side, i * side, side, side);
        const auto pf = patch_features(structure(box).clone());
        for (int k = 0; k < 18; ++k) f[i * nc + j][scale * 18 + k] = pf[k];
        if (scale == 0) sharpness[static_cast<size_t>(i) * nc + j] = cv::mean(sigma(box))[0];
      }
    cv::Mat half;  // the second scale: half size (area averaging)
    cv::resize(image, half, cv::Size(image.cols / 2, image.rows / 2), 0, 0, cv::INTER_AREA);
    image = half;
  }
  const double sharpest = *std::max_element(sharpness.begin(), sharpness.end());
  std::vector<int64_t> keep;
  for (int64_t p = 0; p < features.size(0); ++p) {
    const bool finite = torch::isfinite(features[p]).all().item<bool>();
    if (finite && (!sharp_only || sharpness[p] > sharpness_threshold * sharpest)) keep.push_back(p);
  }
  return features.index_select(0, torch::tensor(keep, torch::kInt64));
}

NiqeModel fit_niqe(const std::vector<std::filesystem::path>& images,
                   const std::function<torch::Tensor(const std::filesystem::path&)>& load, int64_t patch,
                   bool progress) {
  require(!images.empty(), "fit-niqe", "no images to fit on");
  NiqeModel m;
  m.patch = patch;
  std::vector<torch::Tensor> rows(images.size());
  Progress bar("fit-niqe", static_cast<int64_t>(images.size()), progress);
  const int workers = all_cores();
  parallel_for_index(static_cast<int64_t>(images.size()), workers, [&](int64_t i) {
    rows[i] = niqe_features(niqe_gray(load(images[i])), patch, true, m.sharpness_threshold);
    bar.tick();
  });
  bar.finish();
  const auto all = torch::cat(rows);
  require(all.size(0) > kFeatures, "fit-niqe",
          "only " + std::to_string(all.size(0)) + " sharp patches: more (or larger) photographs are needed");
  std::tie(m.mean, m.cov) = mean_and_cov(all);
  m.images = static_cast<int64_t>(images.size());
  m.patches = all.size(0);
  return m;
}

double niqe_score(const NiqeModel& model, const torch::Tensor& image) {
  const auto features = niqe_features(niqe_gray(image), model.patch);
  if (features.size(0) < 2) return std::nan("");
  const auto [mean, cov] = mean_and_cov(features);
  const auto d = (model.mean - mean).unsqueeze(1);  // {36,1}
  const auto inv = torch::linalg::pinv((model.cov + cov) / 2);
  return std::sqrt(std::max(0.0, d.t().matmul(inv).matmul(d).item<double>()));
}

void save_niqe(const std::filesystem::path& path, const NiqeModel& m) {
  auto scalar = [](double v) { return torch::full({1, 1}, v, torch::kFloat64); };
  write_mat(path, {{"mu_prisparam", m.mean.reshape({1, kFeatures})},
                   {"cov_prisparam", m.cov},
                   {"patch_size", scalar(static_cast<double>(m.patch))},
                   {"sharpness_threshold", scalar(m.sharpness_threshold)},
                   {"images", scalar(static_cast<double>(m.images))},
                   {"patches", scalar(static_cast<double>(m.patches))}});
}

NiqeModel load_niqe(const std::filesystem::path& path) {
  MatReader mat(path);
  NiqeModel m;
  m.mean = mat.read("mu_prisparam", {1, kFeatures}).reshape({kFeatures});
  m.cov = mat.read("cov_prisparam", {kFeatures, kFeatures});
  m.patch = static_cast<int64_t>(mat.read_scalar("patch_size"));
  require(m.patch >= 8 && m.patch % 2 == 0, path, "patch_size must be even and at least 8");
  m.sharpness_threshold = mat.has("sharpness_threshold") ? mat.read_scalar("sharpness_threshold") : 0.75;
  m.images = mat.has("images") ? static_cast<int64_t>(mat.read_scalar("images")) : 0;
  m.patches = mat.has("patches") ? static_cast<int64_t>(mat.read_scalar("patches")) : 0;
  require(torch::isfinite(m.mean).all().item<bool>() && torch::isfinite(m.cov).all().item<bool>(), path,
          "the NIQE model holds NaN or infinite values");
  return m;
}

}  // namespace flatnet
