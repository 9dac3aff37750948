// The data-consistency step (recon/data_consistency.hpp, eq. 1): a picture the capture fully explains
// is left as it is, whatever the exposure; a picture that misses the scene's colour is moved toward
// the truth; a capture with no usable exposure keeps the network's picture; bad strengths are named.
// As a layer (model.consistency) it is differentiable, finite on black pixels, and a generator
// trains through it on whole scenes.
#include "catch_torch.hpp"

#include "consistency_bench.hpp"
#include "io/camera_config.hpp"
#include "io/image.hpp"
#include "recon/data_consistency.hpp"
#include "train/gan_trainer.hpp"

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

TEST_CASE("the data-consistency layer: the step's pictures, a finite gradient on black pixels",
          "[recon][consistency]") {
  Bench b;
  const DataConsistency step(b.calib, b.camera, {3.0, 1.0});
  const auto y = b.capture(b.rgb, 2.0);
  auto picture = linear_to_srgb(0.5 * b.rgb);
  picture.narrow(3, 0, 5).zero_();  // black columns: the display curve's slope is infinite at 0
  picture.requires_grad_(true);
  const auto layer = step.correct(y, picture);
  CHECK(torch::allclose(layer.detach(), step(y, picture.detach()), 0, 1e-6));
  layer.square().sum().backward();
  CHECK(torch::isfinite(picture.grad()).all().item<bool>());
  CHECK(picture.grad().abs().sum().item<double>() > 0);
}

TEST_CASE("a generator trains through the data-consistency layer, on whole scenes only", "[train][consistency]") {
  Bench b;
  const DataConsistency layer(b.calib, b.camera, {3.0, 0.0});
  auto gen = at::detail::createCPUGenerator(5);
  const auto scenes = 0.1 + 0.8 * at::rand({2, 3, kScene, kScene}, gen).to(torch::kFloat64);
  std::vector<torch::Tensor> meas;
  for (int64_t i = 0; i < 2; ++i) meas.push_back(b.capture(scenes[i].unsqueeze(0), 1.0)[0]);
  const Batch batch{torch::stack(meas), linear_to_srgb(scenes).to(torch::kFloat32), 0};  // {2,4,h,w}, {2,3,N,N}
  auto g = test::small_generator();
  Discriminator d(DiscriminatorOptions{});
  Vgg16Features none(nullptr);
  torch::optim::Adam opt_g(g->parameters(), 3e-3), opt_d(d->parameters(), 1e-3);
  TrainOptions t;
  t.w_mse = 1, t.w_ssim = 0, t.w_perceptual = 0, t.w_adversarial = 0, t.crop = 0, t.bf16 = false;
  const auto first = gan_step(g, d, none, opt_g, opt_d, t, batch, 0, nullptr, &layer).mse;
  double last = first;
  for (int64_t step = 1; step < 40; ++step)
    last = gan_step(g, d, none, opt_g, opt_d, t, batch, step, nullptr, &layer).mse;
  INFO(first << " -> " << last);
  CHECK(std::isfinite(last));
  CHECK(last < 0.7 * first);
  // What the losses saw is the corrected picture: validation scores it the same way.
  std::vector<Sample> val(2);
  for (int64_t i = 0; i < 2; ++i) val[i].meas = batch.meas[i], val[i].gt = batch.gt[i];
  const auto with = validate(g, val, 2, {}, 0, &layer), without = validate(g, val, 2, {}, 0);
  CHECK(with.psnr != Approx(without.psnr));
  // The correction needs the whole scene: a crop is refused, naming the setting.
  t.crop = 8;
  CHECK_THROWS_WITH(gan_step(g, d, none, opt_g, opt_d, t, batch, 40, nullptr, &layer), Contains("train.crop"));
}
