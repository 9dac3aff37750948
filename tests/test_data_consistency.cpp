// The data-consistency step (recon/data_consistency.hpp, eq. 1): a picture the capture fully explains
// is left as it is, whatever the exposure; a picture that misses the scene's colour is moved toward
// the truth; a capture with no usable exposure keeps the network's picture; bad strengths are named.
#include "catch_torch.hpp"

#include "consistency_bench.hpp"
#include "io/camera_config.hpp"
#include "io/image.hpp"
#include "recon/data_consistency.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

constexpr int64_t kRows = test::kBenchRows, kCols = test::kBenchCols, kScene = test::kBenchScene;

struct Bench : test::SmallCamera {
  torch::Tensor rgb;  // {1,3,N,N} linear light, the scene
  Bench() : SmallCamera(7) {
    // A smooth, coloured scene: red on the left, blue on the right, green in a square.
    rgb = torch::full({1, 3, kScene, kScene}, 0.1);
    rgb.select(1, 0).narrow(2, 0, kScene / 2) += 0.6;
    rgb.select(1, 2).narrow(2, kScene / 2, kScene / 2) += 0.5;
    rgb.select(1, 1).narrow(1, 4, 6).narrow(2, 4, 6) += 0.7;
  }
  torch::Tensor capture(const torch::Tensor& scene_rgb, double exposure) const {  // {1,4,h,w}
    const auto X = rgb_to_bayer_planes(scene_rgb).to(torch::kFloat64);
    return (exposure * torch::matmul(torch::matmul(calib.P, X), calib.Q.transpose(1, 2))).to(torch::kFloat32);
  }
};

double psnr(const torch::Tensor& a, const torch::Tensor& b) {
  return -10 * std::log10((a - b).square().mean().item<double>());
}

}  // namespace

TEST_CASE("data consistency leaves a picture its capture explains, at any exposure", "[recon][consistency]") {
  Bench b;
  const DataConsistency step(b.calib, b.camera, {});
  const auto picture = linear_to_srgb(b.rgb);
  for (const double exposure : {0.2, 1.0, 7.0}) {
    INFO(exposure);
    const auto out = step(b.capture(b.rgb, exposure), picture);
    CHECK(out.sizes() == picture.sizes());
    CHECK((out - picture).abs().max().item<double>() < 2e-3);
  }
  CHECK(step.measured_share() > 0.5);  // this well-conditioned camera measures most pairs far above lambda
}

TEST_CASE("data consistency moves a washed-out picture toward the scene its capture holds", "[recon][consistency]") {
  Bench b;
  const auto truth = linear_to_srgb(b.rgb);
  // The network's picture, washed out: half of every colour replaced by the pixel's grey.
  const auto grey = b.rgb.mean(1, true).expand_as(b.rgb);
  const auto washed = linear_to_srgb(0.5 * b.rgb + 0.5 * grey);
  const auto y = b.capture(b.rgb, 2.5);
  const double before = psnr(washed, truth);
  for (const double c : {10.0, 1.0}) {
    INFO(c);
    CHECK(psnr(DataConsistency(b.calib, b.camera, {c, 0.0})(y, washed), truth) > before + 10);
  }
  // A strong regulariser leaves more of the network's picture.
  const auto weak = DataConsistency(b.calib, b.camera, {1000.0, 0.0})(y, washed);
  const auto strong = DataConsistency(b.calib, b.camera, {1.0, 0.0})(y, washed);
  CHECK(psnr(weak, washed) > psnr(strong, washed) + 3);
  // The blur keeps the correction's coarse part: still toward the truth.
  const auto blurred = DataConsistency(b.calib, b.camera, {1.0, 1.5})(y, washed);
  CHECK(psnr(blurred, truth) > before + 3);
}

TEST_CASE("data consistency keeps the picture of a capture with no usable exposure, and names bad settings",
          "[recon][consistency]") {
  Bench b;
  const auto picture = linear_to_srgb(b.rgb);
  const DataConsistency step(b.calib, b.camera, {});
  CHECK(torch::allclose(step(torch::zeros({1, 4, kRows, kCols}), picture), picture));
  CHECK(torch::allclose(step(-b.capture(b.rgb, 1.0), picture), picture));  // a negative exposure: not this scene
  CHECK_THROWS_WITH(DataConsistency(b.calib, b.camera, {0.0, 0.0}), Contains("strength"));
  CHECK_THROWS_WITH(DataConsistency(b.calib, b.camera, {NAN, 0.0}), Contains("strength"));
  CHECK_THROWS_WITH(DataConsistency(b.calib, b.camera, {10.0, -1.0}), Contains("blur"));
}

TEST_CASE("a picture's disagreement with its capture: none when the capture explains it, at any exposure",
          "[recon][consistency]") {
  Bench b;
  const DataConsistency step(b.calib, b.camera, {});
  const auto picture = linear_to_srgb(b.rgb);
  for (const double exposure : {0.2, 7.0}) {
    INFO(exposure);
    const auto d = step.disagreement(b.capture(b.rgb, exposure), picture);
    CHECK(d.sizes() == torch::IntArrayRef({1}));
    CHECK(d.item<double>() < 1e-6);
  }
  const auto grey = b.rgb.mean(1, true).expand_as(b.rgb);
  const auto washed = linear_to_srgb(0.5 * b.rgb + 0.5 * grey).requires_grad_(true);
  const auto d = step.disagreement(b.capture(b.rgb, 2.5), washed);
  CHECK(d.item<double>() > 0.01);
  d.sum().backward();  // differentiable in the picture
  CHECK(washed.grad().abs().sum().item<double>() > 0);
}
