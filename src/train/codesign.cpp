#include "train/codesign.hpp"

#include "core/error.hpp"
#include "core/util.hpp"
#include "optics/camera.hpp"
#include "train/options.hpp"

namespace flatnet {

CodePairCameraImpl::CodePairCameraImpl(const CodesignOptions& options) : options_(options) {
  require(options_.lr > 0, "codes.lr", "must be positive");
  require(options_.freeze_at >= 0 && options_.freeze_at <= 1, codes_key(&CodesignOptions::freeze_at),
          "must lie in [0, 1]");
  require(options_.target_throughput > 0 && options_.target_throughput < 1 && options_.throughput_tolerance >= 0,
          codes_key(&CodesignOptions::target_throughput), "needs 0 < target < 1 and a tolerance >= 0");
  const auto start = load_code_pair(options_.init_codes);
  // tanh saturates at +-1: a +-1 code starts at +-0.95, where its gradient is still alive.
  auto logit = [](const torch::Tensor& c) { return torch::atanh(c.to(torch::kFloat32).clamp(-0.95, 0.95)); };
  rows_logit_ = register_parameter("rows_logit", logit(start.rows));
  cols_logit_ = register_parameter("cols_logit", logit(start.cols));
}

std::pair<torch::Tensor, torch::Tensor> CodePairCameraImpl::codes() const {
  auto u = torch::tanh(rows_logit_), v = torch::tanh(cols_logit_);
  if (options_.binary) u = straight_through_sign(u), v = straight_through_sign(v);
  return {u, v};
}

torch::Tensor CodePairCameraImpl::throughput() const {
  const auto [u, v] = codes();
  return code_throughput(u, v);
}

torch::Tensor CodePairCameraImpl::throughput_penalty() const {
  return flatnet::throughput_penalty(throughput(), options_.target_throughput, options_.throughput_tolerance);
}

Rig CodePairCameraImpl::rig() const {
  const auto [u, v] = codes();
  return separable_rig(u, v, options_.camera);
}

torch::Tensor CodePairCameraImpl::capture(const torch::Tensor& scene_linear, at::Generator& gen, bool noise,
                                          const Rig* fixed) const {
  return capture_planes(fixed ? *fixed : rig(), scene_linear, options_.geometry, noise, gen);
}

void write_code_camera(const std::filesystem::path& folder, const CodePairCamera& camera,
                       const CameraConfig& geometry) {
  torch::NoGradGuard no_grad;
  const auto [u, v] = camera->codes();
  std::filesystem::create_directories(folder);
  save_code_pair(folder / "codes.mat", u, v);
  write_code_pair_camera(folder, {u.detach(), v.detach()}, geometry, camera->options().calib_error, 0,
                         "The camera of the co-designed codes in codes.mat (`flatnet train` with codes.learn)",
                         camera->options().camera);
}

}  // namespace flatnet
