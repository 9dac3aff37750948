// A camera known only from its calibration (a real camera: no true response to simulate with) is
// simulated through it (optics/camera.hpp calibration_rig): its captures hold the coded light
// P X Q^T, the open part's light open_light * mean(X) as each plane's level, and the noise the camera
// file's noise model states, as the camera fit measures it after preprocessing, rotation included.
// And the noise model is recovered from such captures (optics/camera_fit.hpp fit_noise_model).
#include <cmath>

#include "core/error.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"
#include "optics/camera.hpp"
#include "optics/camera_fit.hpp"
#include "shadow_factor.hpp"

#include "catch_torch.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

constexpr int64_t kScene = 256;

// The shadow factor in all four channels, at 0.015 per unit of code: a scene of mean 0.3 gives a
// coded light of a few percent of full scale. {4,rows,N}
torch::Tensor shadow_factor(int64_t rows, uint64_t seed) {
  return (0.015 * test::shadow_factor(rows, kScene, seed)).unsqueeze(0).expand({4, rows, kScene}).contiguous();
}

CameraConfig calibrated_camera(double rotation) {
  CameraConfig camera;
  camera.name = "calibrated";
  camera.raw.rotation = rotation;
  camera.calibration = "calib.mat";  // named only; the tests hand the calibration over
  camera.noise_gain = 4e-5, camera.noise_floor = 9e-6, camera.dark = 0;
  camera.open_light = 1.0;  // levels up to 0.4 of full scale: none saturates
  return camera;
}

// A scene with edges, its light `exposure` times a [0, 1] pattern, {3,N,N} linear.
torch::Tensor scene(double exposure, uint64_t seed) {
  auto gen = at::detail::createCPUGenerator(seed);
  auto X = torch::upsample_bilinear2d(at::rand({1, 3, 8, 8}, gen), {kScene, kScene}, false)[0];
  X.narrow(1, 40, 90).narrow(2, 60, 120) += 0.5;
  return exposure * X / X.max();
}

}  // namespace

TEST_CASE("a calibration rig's captures hold the calibration's coded light and the open light as the level",
          "[optics][calibration-rig]") {
  const auto camera = calibrated_camera(0.0);
  const Calibration calib{shadow_factor(500, 1).to(torch::kFloat64), shadow_factor(620, 2).to(torch::kFloat64)};
  const auto rig = calibration_rig(calib, camera);
  const auto X = scene(0.5, 3);
  const auto raw = simulate_raw_linear(rig, X, false).to(torch::kFloat32) / 65535.0f;
  const auto window = raw_window(raw, camera.raw);                 // {4,500,620}
  const auto planes = rgb_to_bayer_planes(X).to(torch::kFloat64);  // {4,N,N}
  // The level: open_light times the scene's mean, per plane (the coded light has zero mean: P is centred).
  const auto level = window.mean({1, 2}).to(torch::kFloat64);
  const auto expected_level = camera.open_light * planes.mean({1, 2});
  CHECK((level - expected_level).abs().max().item<double>() < 2e-3);
  CHECK(expected_level.min().item<double>() > 0.1);
  // The coded light: P X Q^T, to the 10-bit ADC's rounding (1 / 1023 full scale).
  const auto coded = torch::matmul(torch::matmul(calib.P, planes), calib.Q.transpose(1, 2));
  const auto centred = without_level(double_centre(window, Centring::plane), Centring::plane).to(torch::kFloat64);
  CHECK((centred - coded).abs().max().item<double>() < 1.5 / 1023);
  CHECK(coded.abs().max().item<double>() > 8.0 / 1023);  // a test of the coded light, not of zeros
}

TEST_CASE("a calibration rig's noise is the camera file's noise model after preprocessing with its rotation",
          "[optics][calibration-rig]") {
  // FlatNet's prototype's angle: its bilinear rotation keeps about half of white noise's variance,
  // which the rig makes up for, so the camera fit measures the file's model on its captures.
  const auto camera = calibrated_camera(0.00174);
  const Calibration calib{shadow_factor(500, 1).to(torch::kFloat64), shadow_factor(620, 2).to(torch::kFloat64)};
  const auto rig = calibration_rig(calib, camera);
  const CameraFit fit(calib, camera);
  std::vector<NoiseSample> samples;
  int i = 0;
  for (const double exposure : {0.15, 0.3, 0.5, 0.7}) {
    auto gen = at::detail::createCPUGenerator(10 + static_cast<uint64_t>(i++));
    const auto raw = simulate_raw_linear(rig, scene(exposure, 4), true, gen).to(torch::kFloat32) / 65535.0f;
    const auto result = fit.measure(raw);
    INFO("exposure " << exposure << ": fit " << result.fit);
    CHECK(result.judged);
    CHECK(result.fit > 0.9);
    CHECK(result.fit < 1.1);
    const auto window = raw_window(raw, camera.raw);
    samples.push_back(
        {without_level(double_centre(window, Centring::plane), Centring::plane), window.mean({1, 2}), 0.0});
  }
  // The noise model back from the captures: the slope within 15 %, the floor within 30 %.
  const auto noise = fit_noise_model(samples, calib.P, calib.Q);
  REQUIRE(noise.found);
  CHECK(noise.noise_gain == Approx(camera.noise_gain).epsilon(0.15));
  CHECK(noise.noise_floor + noise.noise_gain * noise.dark == Approx(camera.noise_floor).epsilon(0.3));
  CHECK(noise.fit_threshold >= 1.0);
  CHECK(noise.fits.size() == 4);
}

TEST_CASE("a camera with no rig and no open light cannot be simulated and says what it lacks",
          "[optics][calibration-rig]") {
  auto camera = calibrated_camera(0.0);
  camera.open_light = 0;
  CHECK_FALSE(can_simulate(camera));
  CHECK_THROWS_WITH(load_camera_rig(camera), Contains("open_light"));
  camera.open_light = 3.7;
  camera.noise_gain = 0;
  const Calibration calib{shadow_factor(500, 1).to(torch::kFloat64), shadow_factor(620, 2).to(torch::kFloat64)};
  CHECK_THROWS_WITH(calibration_rig(calib, camera), Contains("noise model"));
  camera.noise_gain = 4e-5;
  const Calibration wrong{shadow_factor(400, 1).to(torch::kFloat64), shadow_factor(620, 2).to(torch::kFloat64)};
  CHECK_THROWS_WITH(calibration_rig(wrong, camera), Contains("does not match"));
}
