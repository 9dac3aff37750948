#include "train/codesign.hpp"

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/mat.hpp"
#include "optics/camera.hpp"

namespace flatnet {

namespace {

torch::Tensor binarised(const torch::Tensor& x) { return x + (torch::sign(x) - x).detach(); }  // straight-through

}  // namespace

CodePairCameraImpl::CodePairCameraImpl(const CodesignOptions& options) : options_(options) {
  require(options_.lr > 0, "codes.lr", "must be positive");
  require(options_.freeze_at >= 0 && options_.freeze_at <= 1, "codes.freeze_at", "must lie in [0, 1]");
  require(options_.target_throughput > 0 && options_.target_throughput < 1 && options_.throughput_tolerance >= 0,
          "codes.target_throughput", "needs 0 < target < 1 and a tolerance >= 0");
  const auto start = load_code_pair(options_.init_codes);
  // tanh saturates at +-1: a +-1 code starts at +-0.95, where its gradient is still alive.
  auto logit = [](const torch::Tensor& c) { return torch::atanh(c.to(torch::kFloat32).clamp(-0.95, 0.95)); };
  rows_logit_ = register_parameter("rows_logit", logit(start.rows));
  cols_logit_ = register_parameter("cols_logit", logit(start.cols));
}

std::pair<torch::Tensor, torch::Tensor> CodePairCameraImpl::codes() const {
  auto u = torch::tanh(rows_logit_), v = torch::tanh(cols_logit_);
  if (options_.binary) u = binarised(u), v = binarised(v);
  return {u, v};
}

torch::Tensor CodePairCameraImpl::throughput() const {
  const auto [u, v] = codes();
  return (1 + u.mean() * v.mean()) / 2;  // the mask (1 + u v^T) / 2's mean transmittance
}

torch::Tensor CodePairCameraImpl::throughput_penalty() const {
  const auto excess =
      torch::relu(torch::abs(throughput() - options_.target_throughput) - options_.throughput_tolerance);
  return 100.0 * excess.pow(2);
}

Rig CodePairCameraImpl::rig() const {
  const auto [u, v] = codes();
  return separable_rig(u, v, options_.camera);
}

torch::Tensor CodePairCameraImpl::capture(const torch::Tensor& scene_linear, at::Generator& gen, bool noise,
                                          const Rig* fixed) const {
  return capture_planes(fixed ? *fixed : rig(), scene_linear, options_.geometry, noise, gen);
}

void write_codes(const std::filesystem::path& path, const CodePairCamera& camera) {
  torch::NoGradGuard no_grad;
  const auto [u, v] = camera->codes();
  write_mat(path, {{"code_rows", u.detach().to(torch::kFloat64).view({-1, 1})},
                   {"code_cols", v.detach().to(torch::kFloat64).view({-1, 1})}});
}

void write_code_camera(const std::filesystem::path& folder, const CodePairCamera& camera, CameraConfig geometry) {
  torch::NoGradGuard no_grad;
  std::filesystem::create_directories(folder);
  const auto [u, v] = camera->codes();
  const auto rig = separable_rig(u.to(torch::kFloat64), v.to(torch::kFloat64), camera->options().camera);
  write_codes(folder / "codes.mat", camera);
  save_rig(folder / "rig.mat", rig);
  save_calibration(folder / "calib.mat", calibration_of(rig, geometry.raw.crop, camera->options().calib_error, 0));
  geometry.name = folder.filename().string();
  write_text_atomically(folder / "camera.yaml", "# The camera of the co-designed codes in codes.mat (`flatnet train` with codes.learn)\n" +
                                                    camera_geometry_yaml(geometry) +
                                                    "calibration: calib.mat\nrig: rig.mat\n");
}

}  // namespace flatnet
