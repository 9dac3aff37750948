// optics/: mask codes, the camera model against golden captures, calibration.
#include "catch_torch.hpp"

#include "io/camera_config.hpp"
#include "core/util.hpp"
#include "helpers.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "io/raw.hpp"
#include "optics/calibrate.hpp"
#include "optics/camera.hpp"
#include "optics/codes.hpp"
#include "optics/separable_camera.hpp"
#include "optics/simulator.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

TEST_CASE("MLS: length 2^n-1, balanced, two-valued cyclic autocorrelation", "[optics][codes]") {
  for (int n : {3, 5, 9}) {
    auto s = mls(n);
    const int N = (1 << n) - 1;
    REQUIRE(static_cast<int>(s.size()) == N);
    CHECK(std::accumulate(s.begin(), s.end(), 0) == 1);  // one more +1 than -1
    for (int lag = 0; lag < N; ++lag) {
      int acc = 0;
      for (int i = 0; i < N; ++i) acc += s[i] * s[(i + lag) % N];
      CHECK(acc == (lag == 0 ? N : -1));
    }
  }
  CHECK_THROWS_WITH(mls(1), Contains("2..24"));
}

TEST_CASE("FlatNet's 02 pattern and Hadamard matrices", "[optics][codes]") {
  auto p = flatnet_m02_pattern();
  REQUIRE(p.size() == 31);
  CHECK(std::accumulate(p.begin(), p.end(), 0) == 21);
  auto H = hadamard(16);
  CHECK(torch::equal(torch::matmul(H, H.t()), 16 * torch::eye(16, torch::kFloat64)));
  CHECK_THROWS(hadamard(12));
}

TEST_CASE("Toeplitz PhiL from a code: one feature shift per scene pixel", "[optics][codes]") {
  MaskGeometry g;
  g.feature_um = 10;
  g.pixel_pitch_um = 10;  // one sensor pixel per feature: shifts are whole pixels
  g.sensor_pixels = 100;
  g.scene_pixels = 20;
  auto code = mls(7);
  auto phi = toeplitz_phi(code, g);
  REQUIRE(phi.sizes() == torch::IntArrayRef({100, 20}));
  using torch::indexing::Slice;
  // column j+1 is column j moved up by one pixel: phi[i, j+1] == phi[i+1, j]
  CHECK(torch::equal(phi.index({Slice(0, 99), Slice(1, 20)}), phi.index({Slice(1, 100), Slice(0, 19)})));
  CHECK(phi.abs().max().item<double>() == 1.0);
}

TEST_CASE("calibration-free matrices: Toeplitz-like with the geometry's slope, sigma_max 0.5", "[optics][codes]") {
  auto phi = calibration_free_phi(60, 16, 1.0, 3);
  using torch::indexing::Slice;
  CHECK(torch::allclose(phi.index({Slice(1, 60), Slice(1, 16)}), phi.index({Slice(0, 59), Slice(0, 15)})));
  CHECK(torch::linalg_matrix_norm(phi, 2).item<double>() == Approx(0.5));
  CHECK(torch::equal(phi, calibration_free_phi(60, 16, 1.0, 3)));
  MaskGeometry g;  // the reference camera: 20 um features over 10.6 um pixels
  CHECK(geometry_slope(g) == Approx(20.0 / 10.6));
}

TEST_CASE("FlatNet's released calibration-free matrices load per channel", "[optics][codes][shared][solo]") {
  const auto f = test::shared_dir() / "data" / "flatnet" / "phil_toep_slope22.mat";
  if (!std::filesystem::exists(f)) SKIP_TEST(f.string() + " not present");
  auto phil = load_flatnet_toeplitz(f, "phil");
  CHECK(phil.sizes() == torch::IntArrayRef({4, 500, 256}));
  CHECK(torch::linalg_matrix_norm(phil[0], 2).item<double>() == Approx(0.5).epsilon(1e-3));
  REQUIRE_THROWS_WITH(load_flatnet_toeplitz(f, "phir"), Contains("missing variable 'phir'"));
}

TEST_CASE("noise-free simulator reproduces every golden capture within one ADC code", "[optics][camera][golden]") {
  const auto rig = load_rig(test::rig_path());
  int checked = 0;
  for (const auto& scene_path : list_images(test::data_dir() / "golden", {".png"})) {
    const auto stem = scene_path.stem().string();
    if (stem.size() < 6 || stem.substr(stem.size() - 6) != "_scene") continue;
    auto golden_path = scene_path.parent_path() / (stem.substr(0, stem.size() - 6) + "_raw.png");
    auto raw = simulate_raw(rig, read_rgb(scene_path), /*noise=*/false);
    auto golden = read_gray16(golden_path);
    INFO(golden_path);
    const int worst = (raw - golden).abs().max().item<int>();
    CHECK(worst <= 64);
    ++checked;
  }
  CHECK(checked == 4);
}

TEST_CASE("noisy captures are deterministic per seed and unbiased", "[optics][camera]") {
  const auto rig = load_rig(test::rig_path());
  auto scene = read_rgb(test::data_dir() / "golden" / "bsds_16052_scene.png");
  auto a = simulate_raw(rig, scene, true, at::detail::createCPUGenerator(5));
  auto b = simulate_raw(rig, scene, true, at::detail::createCPUGenerator(5));
  auto c = simulate_raw(rig, scene, true, at::detail::createCPUGenerator(6));
  auto clean = simulate_raw(rig, scene, false);
  CHECK(torch::equal(a, b));
  CHECK_FALSE(torch::equal(a, c));
  auto d = (a - clean).to(torch::kFloat64) / 64.0;  // in ADC codes
  CHECK(std::abs(d.mean().item<double>()) < 0.05);
  CHECK(d.std().item<double>() > 0.5);  // ~ sqrt(S * full_well) / full_well * 1023 ~ 2-3 codes
  CHECK(d.std().item<double>() < 5.0);
}

TEST_CASE("calibration recovers P and Q exactly from noise-free rank-1 captures", "[optics][calibrate]") {
  // A small synthetic camera: random P {h,N}, Q {w,N}; captures are exactly P X Q^T (centred).
  const int64_t N = 16, h = 30, w = 36;
  auto gen = at::detail::createCPUGenerator(1);
  Calibration truth{at::randn({4, h, N}, gen, torch::kFloat64), at::randn({4, w, N}, gen, torch::kFloat64)};
  std::map<std::string, torch::Tensor> patterns;
  for (auto& p : calibration_patterns(N, 255)) patterns[p.name] = p.image.to(torch::kFloat64);
  REQUIRE(patterns.size() == 4 * N);
  auto capture = [&](const std::string& name) {
    return torch::matmul(torch::matmul(truth.P, patterns.at(name)), truth.Q.transpose(1, 2));
  };
  auto est = estimate_calibration(N, capture, 255, false);
  auto err = calibration_error(est, truth);
  CHECK(err.p < 1e-8);
  CHECK(err.q < 1e-8);
  CHECK(err.forward < 1e-8);
}

TEST_CASE("calibrating the simulated rig through its ADC: about 1% error", "[optics][calibrate][slow]") {
  // Noise-free, so the test is deterministic; what remains is ADC quantisation and the open-mask
  // (vignetting) light. With noise, `flatnet calibrate --average K` reports its own error.
  const auto camera = load_camera_config(default_camera_path());
  const auto rig = load_rig(camera.rig);
  auto capture =
      rig_pattern_capture(rig, camera.raw, kDefaultPatternLevel, /*noise=*/false, 1, at::detail::createCPUGenerator(0));
  auto est = estimate_calibration(camera.scene_size, capture, kDefaultPatternLevel, false);
  auto err = calibration_error(est, ideal_calibration(rig, camera.raw));
  WARN("relative error: P " << err.p << ", Q " << err.q << ", forward " << err.forward);
  CHECK(err.p < 0.03);
  CHECK(err.q < 0.03);
  CHECK(err.forward < 0.03);
}

TEST_CASE("a rig with NaN in its response is refused by name, never simulated", "[optics][rig]") {
  test::Scratch s("nan_rig");
  auto write_rig = [&](const std::filesystem::path& path, bool poison) {
    std::map<std::string, torch::Tensor> v;
    for (const char* c : kChannelNames) {
      v[std::string("PhiL_") + c] = torch::rand({4, 3}, torch::kFloat64);
      v[std::string("PhiR_") + c] = torch::rand({5, 3}, torch::kFloat64);
      v[std::string("gain_") + c] = torch::ones({1, 1}, torch::kFloat64);
    }
    v["vig_rows"] = torch::ones({4, 1}, torch::kFloat64);
    v["vig_cols"] = torch::ones({5, 1}, torch::kFloat64);
    for (const char* k : {"full_well", "read_noise", "dark", "adc_bits"})
      v[k] = torch::full({1, 1}, 10.0, torch::kFloat64);
    if (poison) v["PhiR_gr"][2][1] = std::nan("");
    write_mat(path, v);
  };
  write_rig(s.dir / "good.mat", false);
  CHECK_NOTHROW(load_rig(s.dir / "good.mat"));
  write_rig(s.dir / "bad.mat", true);
  CHECK_THROWS_WITH(load_rig(s.dir / "bad.mat"), Catch::Matchers::Contains("bad.mat") &&
                                                     Catch::Matchers::Contains("PhiR") &&
                                                     Catch::Matchers::Contains("NaN"));
}

TEST_CASE("a camera from codes: the MLS pair rebuilds rig.mat, and gradients reach both codes", "[optics][separable]") {
  MatReader codes(test::source_dir() / "models" / "camera" / "codes_mls.mat");
  const auto u = codes.read("code_rows").flatten(), v = codes.read("code_cols").flatten();
  REQUIRE(u.numel() == 511);
  const auto rig = separable_rig(u, v);
  const auto shipped = load_rig(test::rig_path());
  CHECK((rig.phil.to(torch::kFloat32) - shipped.phil).abs().max().item<double>() < 1e-6);
  CHECK((rig.phir.to(torch::kFloat32) - shipped.phir).abs().max().item<double>() < 1e-6);
  CHECK(torch::allclose(rig.gain.to(torch::kFloat32), shipped.gain, 1e-6, 0));
  // The pedestal: rig.mat rounds the MLS pair's mean transmittance (1 + 1/511^2) / 2 to 0.5.
  CHECK(torch::allclose(rig.vig_rows.to(torch::kFloat32), shipped.vig_rows, 1e-5, 0));
  CHECK(torch::allclose(rig.vig_cols.to(torch::kFloat32), shipped.vig_cols, 1e-5, 0));

  // Another pair changes the camera, and the construction is differentiable in both codes.
  auto a = (torch::rand({511}, torch::kFloat64) * 2 - 1).requires_grad_(),
       b = (torch::rand({511}, torch::kFloat64) * 2 - 1).requires_grad_();
  const auto other = separable_rig(a, b);
  CHECK((other.phil - rig.phil).abs().max().item<double>() > 0.1);
  (other.phil.pow(2).sum() + other.phir.pow(2).sum() + other.vig_rows.sum()).backward();
  CHECK(a.grad().abs().sum().item<double>() > 0);
  CHECK(b.grad().abs().sum().item<double>() > 0);

  // Its calibration: the centred window with the requested relative error (the shipped calib.mat: 3 %).
  const CameraConfig camera;
  const auto exact = calibration_of(rig, camera.raw.crop, 0.0, 0);
  const auto noisy = calibration_of(rig, camera.raw.crop, 0.03, 0);
  const auto shipped_calib = load_calibration(test::calib_path(), camera);
  for (int c = 0; c < 4; ++c) {
    INFO("channel " << c);
    CHECK((noisy.P[c] - exact.P[c]).norm().item<double>() / exact.P[c].norm().item<double>() ==
          Approx(0.03).epsilon(1e-6));
    CHECK((shipped_calib.P[c] - exact.P[c]).norm().item<double>() / exact.P[c].norm().item<double>() ==
          Approx(0.03).epsilon(0.02));
    CHECK((shipped_calib.Q[c] - exact.Q[c]).norm().item<double>() / exact.Q[c].norm().item<double>() ==
          Approx(0.03).epsilon(0.02));
    CHECK(exact.P[c].mean(0).abs().max().item<double>() < 1e-12);  // centred columns
  }
}

TEST_CASE("the simulator's errors name its options by key, never by a CLI flag", "[optics][errors]") {
  const auto rig = load_rig(test::rig_path());
  test::Scratch s("sim_keys");
  SimulateOptions o;
  o.images = s.dir;
  o.out = s.dir / "out";
  o.exposure = -1;
  CHECK_THROWS_WITH(simulate_dataset(rig, o), Contains("simulate.exposure") && !Contains("--"));
  o.exposure = 1;
  o.val_fraction = 2;
  CHECK_THROWS_WITH(simulate_dataset(rig, o),
                    Contains("simulate.val_fraction: must be within [0, 1]") && !Contains("--"));
}
