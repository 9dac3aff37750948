#include "optics/rotation_estimate.hpp"

#include <algorithm>
#include <cmath>

#include "core/error.hpp"
#include "io/raw.hpp"

namespace flatnet {

namespace {

using torch::indexing::Slice;

// Differences over 4 pixels along rows and columns of {4,m,k}, on the interior {4,m-4,k-4}. A model
// identified from a hundred photographs misses the pixel-scale detail of the code; the smoother
// gradient follows the true one better (3 times the slope k of central differences on a noisy bench).
std::pair<torch::Tensor, torch::Tensor> interior_gradients(const torch::Tensor& u) {
  const auto d_rows = (u.slice(1, 4) - u.slice(1, 0, -4)).slice(2, 2, -2) / 4;
  const auto d_cols = (u.slice(2, 4) - u.slice(2, 0, -4)).slice(1, 2, -2) / 4;
  return {d_rows, d_cols};
}

// g {4,h,w} less its least-squares part along a and b per plane.
torch::Tensor without_translation(const torch::Tensor& g, const torch::Tensor& a, const torch::Tensor& b) {
  const auto basis = torch::stack({a.flatten(1), b.flatten(1)}, 1);  // {4,2,hw}
  const auto gram = torch::matmul(basis, basis.transpose(1, 2)) +
                    1e-12 * torch::eye(2, basis.options()).unsqueeze(0) * basis.square().sum({1, 2}).view({4, 1, 1});
  const auto coef = torch::linalg_solve(gram, torch::matmul(basis, g.flatten(1).unsqueeze(2)));  // {4,2,1}
  return g - torch::matmul(coef.transpose(1, 2), basis).view(g.sizes());
}

// The model's capture (calibrate_dataset.hpp eq. 2) of scene planes {4,N,N}: P Xz Q^T + s M.
torch::Tensor predicted(const DatasetCalibration& fit, const torch::Tensor& scene) {
  auto X = scene.to(torch::kFloat64);
  if (fit.colour_mix.defined()) X = scene_through_mix(X, fit.colour_mix.to(torch::kFloat64));
  const auto s = X.sum({1, 2}, true);  // {4,1,1}
  const auto Xz = X - s / static_cast<double>(X.size(1) * X.size(2));
  return torch::matmul(torch::matmul(fit.calib.P, Xz), fit.calib.Q.transpose(1, 2)) +
         s * fit.uniform_response.to(torch::kFloat64);  // {4,m,k}
}

}  // namespace

torch::Tensor window_inside_plane(int64_t height, int64_t width, const RawGeometry& g) {
  return rotated_window(torch::ones({1, height, width}), g)[0] > 1 - 1e-5;  // {rows,cols}
}

double rotation_residual_projection(int64_t count, const std::function<WindowPair(int64_t)>& load,
                                    const DatasetCalibration& fit, const std::array<int64_t, 2>& origin) {
  require_option(count >= 1, "calibrate.rotation", "no pairs to estimate the rotation from");
  double num = 0, den = 0;
  for (int64_t i = 0; i < count; ++i) {
    const auto pair = load(i);
    const auto window = pair.window.to(torch::kFloat64);  // {4,m,k}
    const auto m = window.size(1), k = window.size(2);
    const auto Y = double_centre(window, Centring::plane);
    const auto model = predicted(fit, pair.scene);
    // The window the model stands for: its centred prediction plus the window's own row and column
    // means (the part centring removes; averages, so nearly free of the pixels' noise).
    const auto u = model + window.mean(2, true) + window.mean(1, true);
    const auto [d_rows, d_cols] = interior_gradients(u);  // {4,m-4,k-4}
    const auto opts = torch::TensorOptions().dtype(torch::kFloat64);
    const auto r = torch::arange(2, m - 2, opts).add(static_cast<double>(origin[0])).view({1, -1, 1});
    const auto c = torch::arange(2, k - 2, opts).add(static_cast<double>(origin[1])).view({1, 1, -1});
    // (1): G = c' dW/dr - r' dW/dc, centred as the captures are, less its part along the two
    // translations (a shadow a fraction of a pixel off is the fit's error, not a rotation).
    const auto G = without_translation(double_centre(c * d_rows - r * d_cols, Centring::plane),
                                       double_centre(d_rows, Centring::plane), double_centre(d_cols, Centring::plane));
    auto R = (Y - model).slice(1, 2, -2).slice(2, 2, -2);
    if (pair.valid.defined()) R = R * pair.valid.to(torch::kFloat64).slice(0, 2, -2).slice(1, 2, -2);
    num += (R * G).sum().item<double>();
    den += G.square().sum().item<double>();
  }
  require_option(den > 0, "calibrate.rotation", "the captures hold no structure to see a rotation by");
  return num / den;
}

RotationSearch search_rotation(const std::function<double(double)>& project, const RotationSearchOptions& o) {
  require_option(o.fits >= 2 && o.limit > 0 && o.tolerance > 0 && o.first_step > o.tolerance, "calibrate.rotation",
                 "fits >= 2, limit > 0, tolerance > 0 and first_step > tolerance are needed");
  RotationSearch out;
  const auto clamp = [&](double t) {
    return std::clamp(std::clamp(t, o.start - o.limit, o.start + o.limit), -o.bound, o.bound);
  };
  const auto probe = [&](double t) {
    out.probes.push_back({t, project(t)});
    return out.probes.back();
  };
  auto last = probe(o.start);
  // d = k (t - t*) with k unknown (0.02 on a noisy random-code camera, 0.2 on a clean one): a first
  // step of fixed size towards the root, then secants.
  double next = clamp(last.angle - (last.projection > 0 ? o.first_step : -o.first_step));
  while (static_cast<int>(out.probes.size()) < o.fits && std::abs(next - last.angle) >= o.tolerance) {
    const auto now = probe(next);
    const double slope = (now.projection - last.projection) / (now.angle - last.angle);
    if (!std::isfinite(slope) || slope <= 0) {  // no rotation signal the secant can follow
      out.slope_found = false;
      break;
    }
    next = clamp(now.angle - now.projection / slope);
    last = now;
  }
  const double step = std::abs(next - last.angle);
  out.converged = out.slope_found && step < o.tolerance;
  // Out of fits, the last root stands when its step is small against the search's; otherwise the
  // probe whose residual holds the least rotation.
  if (out.slope_found && step < 10 * o.tolerance) {
    out.angle = next;
  } else {
    out.angle = std::min_element(out.probes.begin(), out.probes.end(), [](const auto& a, const auto& b) {
                  return std::abs(a.projection) < std::abs(b.projection);
                })->angle;
  }
  return out;
}

}  // namespace flatnet
