// The camera fit's near-twin test (optics/camera_fit.hpp, coded_leak): another mask on the same sensor,
// whose shadow moves by the same shift per scene pixel, spans nearly the same space as this camera's
// calibration, so the energy it leaves outside is near the noise's; its leak is a coded scene, a few
// strong singular directions, where noise spreads evenly. Full geometry (500x620, N 256) on purpose:
// the statistic's reference is the 41st singular value, inside the noise's bulk only at real sizes.
#include "catch_torch.hpp"

#include <cmath>

#include "io/raw.hpp"
#include "optics/camera_fit.hpp"
#include "shadow_factor.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

constexpr int64_t kRows = 500, kCols = 620, kScene = 256;

torch::Tensor shadow_factor(int64_t rows, uint64_t seed) { return test::shadow_factor(rows, kScene, seed); }

// A smooth scene with edges: a few rectangles on a gradient, {N,N}.
torch::Tensor test_scene() {
  auto X = torch::linspace(0, 1, kScene).view({1, kScene}).expand({kScene, kScene}).clone();
  X.narrow(0, 40, 90).narrow(1, 60, 120) += 0.8;
  X.narrow(0, 150, 70).narrow(1, 20, 200) -= 0.5;
  return X;
}

// Four planes of P X Q^T plus Gaussian noise of `noise` times the coded light's RMS, {4,h,w}.
torch::Tensor capture(const torch::Tensor& P, const torch::Tensor& Q, double noise, uint64_t seed) {
  auto gen = at::detail::createCPUGenerator(seed);
  const auto coded = torch::matmul(torch::matmul(P, test_scene()), Q.t());  // {h,w}
  const double rms = coded.square().mean().sqrt().item<double>();
  return coded.unsqueeze(0).expand({4, kRows, kCols}) + noise * rms * torch::randn({4, kRows, kCols}, gen);
}

torch::Tensor span_basis(const torch::Tensor& F) {  // {rows,N} -> {4,rows,N} orthonormal
  return std::get<0>(torch::linalg_qr(F.to(torch::kFloat64)))
      .to(torch::kFloat32)
      .unsqueeze(0)
      .expand({4, -1, -1})
      .contiguous();
}

}  // namespace

TEST_CASE("the camera fit's coded leak: noise and this camera stay near noise's level, a near twin stands out",
          "[optics][camera-fit]") {
  const auto P = shadow_factor(kRows, 1), Q = shadow_factor(kCols, 2);
  const auto U = span_basis(P), V = span_basis(Q);
  const double noise_level = noise_leak(U, V);
  // Noise alone: the largest over the 41st singular value of a Gaussian matrix of these blocks' shape.
  CHECK(noise_level > 1.05);
  CHECK(noise_level < 1.4);
  const double threshold = 1.1 * noise_level;

  // This camera, at several noise levels: its coded scene lies inside the spans, the leak is noise's.
  for (const double noise : {0.05, 0.3, 1.0}) {
    INFO("noise " << noise);
    CHECK(coded_leak(capture(P, Q, noise, 3), U, V) < threshold);
  }
  // A twin: the same sensor and shift, other codes. Its scene leaks out of the spans, coded.
  const auto P_twin = shadow_factor(kRows, 11), Q_twin = shadow_factor(kCols, 12);
  const auto twin = capture(P_twin, Q_twin, 0.3, 4);
  const double twin_leak = coded_leak(twin, U, V);
  CHECK(twin_leak > 1.5 * threshold);
  // Scale-free (a brighter exposure is the same capture) and blind to row, column and level offsets.
  CHECK(coded_leak(7.0 * twin, U, V) == Approx(twin_leak).epsilon(1e-3));
  const auto offsets =
      torch::linspace(0, 1, kRows).view({1, kRows, 1}) + torch::linspace(0, 2, kCols).view({1, 1, kCols});
  CHECK(coded_leak(twin + offsets, U, V) == Approx(twin_leak).epsilon(1e-3));
  // The open part's light (rank 1 per plane) is set aside however bright it is.
  const auto open_light = 50.0 * torch::outer(torch::rand({kRows}) + 1, torch::rand({kCols}) + 1).unsqueeze(0);
  CHECK(coded_leak(capture(P, Q, 0.3, 5) + open_light, U, V) < threshold);

  // A window too small beside the scene gives no stable reference: not measured (NaN).
  const auto small_U = span_basis(torch::randn({60, 32})), small_V = span_basis(torch::randn({76, 32}));
  CHECK(std::isnan(coded_leak(torch::randn({4, 60, 76}), small_U, small_V)));
}

namespace {

// A raw frame {1000,1240} of a camera with factors P, Q: the coded scene on a level, in [0.1, 0.5] of
// full scale, with the photon and read noise the camera's noise model states.
torch::Tensor raw_frame(const torch::Tensor& P, const torch::Tensor& Q, const CameraConfig& camera, uint64_t seed) {
  auto gen = at::detail::createCPUGenerator(seed);
  const auto coded = torch::matmul(torch::matmul(P, test_scene()), Q.t());  // {h,w}
  const auto light = (0.3 + 0.2 * coded / coded.abs().max()).unsqueeze(0).expand({4, kRows, kCols});
  const auto var = (light - camera.dark) * camera.noise_gain + camera.noise_floor;
  return bayer_merge(light + var.sqrt() * torch::randn({4, kRows, kCols}, gen)).clamp(0, 1);
}

}  // namespace

TEST_CASE("the camera fit flags a near twin's capture by its coded leak and says so", "[optics][camera-fit]") {
  const auto P = shadow_factor(kRows, 1), Q = shadow_factor(kCols, 2);
  CameraConfig camera;
  camera.name = "twin-test";
  camera.raw.raw_height = 2 * kRows, camera.raw.raw_width = 2 * kCols, camera.raw.adc_bits = 16;
  camera.raw.crop = {0, 0, kRows, kCols};
  camera.raw.centring = Centring::level;
  camera.noise_gain = 2.5e-5, camera.noise_floor = 1e-7, camera.dark = 0.02;
  const Calibration calib{P.to(torch::kFloat64).unsqueeze(0).repeat({4, 1, 1}),
                          Q.to(torch::kFloat64).unsqueeze(0).repeat({4, 1, 1})};
  const CameraFit fit(calib, camera);
  REQUIRE(fit.leak_threshold() > 1.0);

  const auto own = fit.measure(raw_frame(P, Q, camera, 1));
  CHECK(own.judged);
  CHECK(own.leak < fit.leak_threshold());
  CHECK(own.matches);

  const auto twin = fit.measure(raw_frame(shadow_factor(kRows, 11), shadow_factor(kCols, 12), camera, 2));
  CHECK(twin.leak > fit.leak_threshold());
  CHECK_FALSE(twin.leak_matches);
  CHECK_FALSE(twin.matches);
  CHECK(fit.excess(twin) > 1.0);
  // What the user reads: the test that failed. A capture whose energy fits and whose leak does not:
  CameraFitResult leaking;
  leaking.fit = 1.0, leaking.leak = 2 * fit.leak_threshold(), leaking.leak_matches = false;
  CHECK(fit.excess(leaking) == Approx(2.0));
  CHECK_THAT(fit.verdict(leaking), Contains("coded leak") && Contains("another mask"));
  CHECK_THAT(fit.verdict(twin), Contains("fit ") && Contains("against <= "));
  CameraFitResult both = leaking;  // both tests fail: both named
  both.fit = 2 * fit.threshold();
  CHECK_THAT(fit.verdict(both), Contains("fit 2") && Contains(", coded leak"));

  // A batch is one camera's captures: judged as a whole by the lower median of its judged captures'
  // excess. A result whose excess is e (its fit e times the threshold):
  const auto with_excess = [&](double e, bool judged = true) {
    CameraFitResult r;
    r.fit = e * fit.threshold(), r.leak = 0, r.judged = judged, r.matches = !judged || e <= 1;
    return r;
  };
  const auto own_batch = judge_batch(fit, {own, own, own});
  CHECK(own_batch.judged == 3);
  CHECK(own_batch.median_excess < 1.0);
  CHECK_FALSE(own_batch.foreign);
  // A twin's batch where two of five pass alone is flagged as a whole (lower median 1.5).
  const auto twins =
      judge_batch(fit, {with_excess(0.9), with_excess(1.5), with_excess(1.6), with_excess(0.95), with_excess(2.0)});
  CHECK(twins.median_excess == Approx(1.5));
  CHECK(twins.foreign);
  // The camera's own batch with two odd captures in it is not: they stay flagged alone.
  CHECK_FALSE(
      judge_batch(fit, {with_excess(0.9), with_excess(0.9), with_excess(0.9), with_excess(3), with_excess(3)}).foreign);
  // Too few judged captures for a batch verdict; unjudged (saturated) ones do not count.
  CHECK_FALSE(judge_batch(fit, {with_excess(2), with_excess(2)}).foreign);
  const auto mostly_saturated =
      judge_batch(fit, {with_excess(2), with_excess(2), with_excess(5, false), with_excess(5, false)});
  CHECK(mostly_saturated.judged == 2);
  CHECK_FALSE(mostly_saturated.foreign);
  CHECK(judge_batch(fit, {}).judged == 0);
  // Even counts take the lower median (the lenient one); a fit that is not a number is a misfit.
  CHECK(judge_batch(fit, {with_excess(0.5), with_excess(0.8), with_excess(1.2), with_excess(1.4)}).median_excess ==
        Approx(0.8));
  CHECK(judge_batch(fit, {with_excess(std::nan("")), with_excess(std::nan("")), with_excess(0.5)}).foreign);

  // A camera file's leak_threshold (an estimated calibration's own spread) raises the bar.
  camera.leak_threshold = 2 * twin.leak;
  const CameraFit lenient(calib, camera);
  CHECK(lenient.leak_threshold() == Approx(2 * twin.leak));
}
