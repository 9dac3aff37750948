#include "recon/data_consistency.hpp"

#include <cmath>
#include <iomanip>
#include <sstream>

#include "core/error.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"
#include "nn/model_spec.hpp"

namespace flatnet {

namespace {
constexpr double kDarkestLight = 1e-6;  // of display white: 0.004 of an 8-bit step after the curve
}  // namespace

DataConsistency::DataConsistency(const Calibration& calib, const CameraConfig& camera, DataConsistencyOptions o)
    : centring_(camera.raw.centring),
      P_(calib.P.to(torch::kFloat32)),
      Q_(calib.Q.to(torch::kFloat32)),
      mix_(camera.colour_mix.empty() ? torch::Tensor() : colour_mix_matrix(camera.colour_mix).to(torch::kFloat32)),
      display_gamma_(camera.display_gamma),
      svd_(separable_inverse(calib.P, calib.Q, camera.tikhonov_lambda)),
      strength_(o.strength) {
  require_option(std::isfinite(o.strength) && o.strength > 0 && o.strength <= 1e3, "infer.data_consistency",
                 "the strength c of the data-consistency step lies in (0, 1000]");
  require_option(std::isfinite(o.blur) && o.blur >= 0 && o.blur <= 64, "infer.consistency_blur",
                 "the correction's blur is 0 (none) to 64 scene pixels");
  const double lambda = camera.tikhonov_lambda;
  const auto s = svd_.sL.unsqueeze(2) * svd_.sR.unsqueeze(1);  // {4,N,N} float64: s_Li s_Rj
  gain_pairs_ = well_measured_pairs(svd_.sL, svd_.sR, lambda).to(torch::kFloat32);
  filter_ = (s / (s.square() + o.strength * o.strength * lambda)).to(torch::kFloat32);
  measured_share_ = (s >= o.strength * std::sqrt(lambda)).to(torch::kFloat64).mean().item<double>();
  if (o.blur > 0) blur_ = correction_blur(o.blur, P_.size(2));
}

torch::Tensor DataConsistency::correction_blur(double sigma, int64_t scene) {
  // Reflection padding needs the kernel's radius (3 sigma) inside the scene.
  const auto problem = consistency_blur_reach_problem(sigma, scene);  // nn/model_spec.hpp
  require_option(problem.empty(), "infer.consistency_blur", problem);
  const auto radius = static_cast<int64_t>(std::ceil(3 * sigma));
  // exp(-(x / sigma)^2 / 2) in float64: a sigma far below a pixel gives the identity (1 at x = 0, 0
  // elsewhere), where 2 sigma^2 would underflow to 0 and 0 / 0 make the kernel NaN.
  const auto x = torch::arange(-radius, radius + 1, torch::kFloat64) / sigma;
  auto g = torch::exp(-x.square() / 2);
  g = (g / g.sum()).to(torch::kFloat32);
  return torch::outer(g, g).expand({4, 1, 2 * radius + 1, 2 * radius + 1}).contiguous();
}

torch::Tensor DataConsistency::to_planes(const torch::Tensor& srgb) const {
  const auto rgb = display_to_light(srgb.to(torch::kFloat32), display_gamma_);  // {B,3,N,N}
  if (!mix_.defined()) return rgb_to_bayer_planes(rgb);
  return torch::einsum("pc,bchw->bphw", {mix_, rgb});  // each plane's shares of the primaries
}

torch::Tensor DataConsistency::from_planes(const torch::Tensor& planes) const {
  const auto rgb = mix_.defined() ? unmix_primaries(planes, mix_.to(torch::kFloat64)) : bayer_planes_to_rgb(planes);
  return light_to_display(rgb, display_gamma_);  // clipped to [0, 1]
}

DataConsistency::Coefficients DataConsistency::coefficients(const torch::Tensor& planes, const torch::Tensor& X) const {
  const auto Y = without_level(planes.to(torch::kFloat32), centring_);      // {B,4,h,w}
  const auto AX = torch::matmul(torch::matmul(P_, X), Q_.transpose(1, 2));  // {B,4,h,w}
  const auto on_pairs = [&](const torch::Tensor& Z) {                       // U_L^T Z U_R
    return torch::matmul(torch::matmul(svd_.ULt, Z), svd_.UR);
  };
  Coefficients c{on_pairs(Y), on_pairs(AX), {}, {}};  // {B,4,N,N}
  // The capture's exposure against the picture's: one gain per capture, least squares on the pairs
  // the camera measures above its noise.
  const auto cX = c.picture.detach();
  const auto a =
      (c.capture * cX * gain_pairs_).sum({1, 2, 3}) / (cX * cX * gain_pairs_).sum({1, 2, 3}).clamp_min(1e-30);
  c.usable = torch::isfinite(a) & (a > 0);
  c.gain = torch::where(c.usable, a, torch::ones_like(a)).view({-1, 1, 1, 1});
  return c;
}

torch::Tensor DataConsistency::operator()(const torch::Tensor& planes, const torch::Tensor& picture) const {
  c10::InferenceMode no_grad;
  return correct(planes, picture);
}

torch::Tensor DataConsistency::correct(const torch::Tensor& planes, const torch::Tensor& picture) const {
  const auto X = to_planes(picture);  // {B,4,N,N}
  const auto c = coefficients(planes, X);
  // (1): the residual's coefficients through the regularised inverse, in the picture's units.
  const auto residual = (c.capture / c.gain - c.picture) * filter_;
  auto correction = torch::matmul(torch::matmul(svd_.VL, residual), svd_.VRt);  // {B,4,N,N}
  if (blur_.defined()) {
    const auto r = blur_.size(2) / 2;
    const std::vector<int64_t> ones{1, 1};
    correction = torch::conv2d(torch::reflection_pad2d(correction, {r, r, r, r}), blur_, torch::Tensor(), ones,
                               std::vector<int64_t>{0, 0}, ones, /*groups=*/4);
  }
  // Light floored just above 0, not at it: the display curve's slope (x^(1/gamma), sRGB's x^(1/2.4))
  // is infinite at 0, and a layer that trains must give a finite gradient on a black pixel.
  const auto corrected = from_planes((X + correction).clamp_min(kDarkestLight));
  // A capture with no usable exposure (dark, or not this camera's) keeps the network's picture.
  return torch::where(c.usable.view({-1, 1, 1, 1}), corrected, picture.to(corrected.scalar_type()));
}

torch::Tensor DataConsistency::disagreement(const torch::Tensor& planes, const torch::Tensor& picture) const {
  const auto c = coefficients(planes, to_planes(picture));
  const auto miss = ((c.capture - c.gain * c.picture).square() * gain_pairs_).sum({1, 2, 3});  // {B}
  return miss / (c.capture.square() * gain_pairs_).sum({1, 2, 3}).clamp_min(1e-30);
}

namespace {

class ConsistentReconstructor final : public Reconstructor {
 public:
  ConsistentReconstructor(std::unique_ptr<Reconstructor> engine, std::shared_ptr<const DataConsistency> step)
      : engine_(std::move(engine)), step_(std::move(step)) {}
  std::string describe() const override {
    std::ostringstream s;
    s << engine_->describe() << " + data consistency (c " << std::setprecision(3) << step_->strength()
      << ": the capture "
      << "decides " << std::setprecision(3) << 100 * step_->measured_share() << " % of singular pairs)";
    return s.str();
  }
  torch::Tensor reconstruct(const torch::Tensor& planes) override {
    return (*step_)(planes, engine_->reconstruct(planes));
  }

 private:
  std::unique_ptr<Reconstructor> engine_;
  std::shared_ptr<const DataConsistency> step_;
};

}  // namespace

std::unique_ptr<Reconstructor> with_data_consistency(std::unique_ptr<Reconstructor> engine, const Calibration& calib,
                                                     const CameraConfig& camera, DataConsistencyOptions options) {
  return with_data_consistency(std::move(engine), std::make_shared<const DataConsistency>(calib, camera, options));
}

std::unique_ptr<Reconstructor> with_data_consistency(std::unique_ptr<Reconstructor> engine,
                                                     std::shared_ptr<const DataConsistency> step) {
  return std::make_unique<ConsistentReconstructor>(std::move(engine), std::move(step));
}

}  // namespace flatnet
