#include "optics/camera_fit.hpp"

#include <cmath>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/raw.hpp"

namespace flatnet {

namespace {

// The largest singular value squared of each {h,w} matrix, by power iteration on R^T R (the
// open part's rank-1 light dominates it when present; otherwise the noise's largest).
torch::Tensor top_singular_squared(const torch::Tensor& R) {
  auto v = torch::ones({R.size(0), R.size(2), 1}, R.options()) / std::sqrt(static_cast<double>(R.size(2)));
  torch::Tensor norm2;
  for (int i = 0; i < 30; ++i) {
    const auto w = torch::matmul(R.transpose(1, 2), torch::matmul(R, v));  // {4,w,1}
    norm2 = (v * w).sum({1, 2});                                           // v^T R^T R v
    v = w / w.norm(2, {1, 2}, true).clamp_min(1e-30);
  }
  return norm2;
}

}  // namespace

CameraFit::CameraFit(const Calibration& calib, const CameraConfig& camera) : camera_(camera) {
  require(camera.knows_noise(), camera.name,
          "this camera has no noise model (noise_gain, noise_floor, dark); `flatnet calibrate --dataset` measures it");
  require(calib.P.dim() == 3 && calib.P.size(0) == 4 && calib.P.size(1) == camera.raw.crop[2] &&
              calib.Q.dim() == 3 && calib.Q.size(1) == camera.raw.crop[3] && calib.P.size(2) == calib.Q.size(2),
          camera.name, "the calibration does not match the camera's crop");
  // Orthonormal bases of P's and Q's column spaces (reduced QR, in float64 for the small columns).
  U_ = std::get<0>(torch::linalg_qr(calib.P.to(torch::kFloat64))).to(torch::kFloat32).contiguous();
  V_ = std::get<0>(torch::linalg_qr(calib.Q.to(torch::kFloat64))).to(torch::kFloat32).contiguous();
  const double h = static_cast<double>(U_.size(1)), w = static_cast<double>(V_.size(1));
  const double n = static_cast<double>(U_.size(2));
  const double dof = (h - 1) * (w - 1) - n * n;
  require(dof > 1000, camera.name, "the capture window is too small beside the scene to test a capture's fit");
  // Chance alone: the pooled energy of 4 * dof noise terms has relative deviation sqrt(2 / (4 dof)).
  // Six deviations, and 1 % for calibration error and the noise model's own.
  threshold_ = 1 + 6 * std::sqrt(2 / (4 * dof)) + 0.01;
}

CameraFitResult CameraFit::measure(const torch::Tensor& raw_unit) const {
  torch::NoGradGuard no_grad;
  const auto& g = camera_.raw;
  const auto window = raw_window(raw_unit, g);                       // {4,h,w}: the light each pixel read
  const auto Y = without_level(double_centre(window, g.centring), g.centring);  // the separable model's planes
  const auto inside = torch::matmul(torch::matmul(U_, torch::matmul(torch::matmul(U_.transpose(1, 2), Y), V_)),
                                    V_.transpose(1, 2));  // {4,h,w}: U U^T Y V V^T
  const auto R = (Y - inside).to(torch::kFloat64);
  const auto unexplained = R.square().sum() - top_singular_squared(R).sum();
  // The noise model, pixel by pixel: clipped pixels carry no noise.
  const auto saturated = window >= 1.0f - 1e-6f;
  const auto var = torch::where(saturated, torch::zeros_like(window),
                                (window - camera_.dark).clamp_min(0) * camera_.noise_gain + camera_.noise_floor)
                       .to(torch::kFloat64);
  const double h = static_cast<double>(window.size(1)), w = static_cast<double>(window.size(2));
  const double n = static_cast<double>(U_.size(2));
  const double dof = (h - 1) * (w - 1) - n * n;
  const auto per_channel_var = var.sum({1, 2});  // {4}
  const auto expected = per_channel_var * (dof / (h * w)) -
                        per_channel_var / (h * w) * std::pow(std::sqrt(h - 1) + std::sqrt(w - 1), 2);
  CameraFitResult r;
  r.fit = unexplained.item<double>() / std::max(1e-30, expected.sum().item<double>());
  r.saturated = saturated.to(torch::kFloat32).mean().item<double>();
  r.matches = std::isfinite(r.fit) && r.fit <= threshold_;
  return r;
}

}  // namespace flatnet
