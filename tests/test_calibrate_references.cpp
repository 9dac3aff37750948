// A calibration recovered from a few direct captures and someone else's reconstructions of them
// (optics/calibrate_references): the exact profile solve agrees with conjugate gradients, a small
// FlatCam-like camera (shift-structured factors, one shift below 0.5 sensor pixels per scene pixel,
// the other positive) is identified from three pairs whose references carry their own gain and offset,
// and each held-out pair is reconstructed from the other pairs' calibration. Flat captures are named.
// A light every capture holds (a flare) is fitted as its own term, written with the calibration, and
// subtracted by classical reconstruction.
#include <cmath>
#include <filesystem>
#include <map>

#include <unistd.h>

#include "catch_torch.hpp"

#include "core/error.hpp"
#include "optics/calibrate_references.hpp"
#include "optics/reference_camera.hpp"
#include "optics/separable_inverse.hpp"
#include "optics/shift_structure.hpp"
#include "io/mat.hpp"
#include "optics/camera.hpp"
#include "recon/reconstructor.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

constexpr int64_t kRows = 120, kCols = 140, kScene = 48;
constexpr double kShiftRows = -0.43, kShiftCols = 0.9;

// Smooth positive scenes with edges, as photographs are: an 8x8 random field enlarged bilinearly,
// plus a bright rectangle.
torch::Tensor scene(uint64_t seed) {
  auto gen = at::detail::createCPUGenerator(seed);
  auto X = torch::upsample_bilinear2d(at::rand({1, 4, 8, 8}, gen).to(torch::kFloat64), {kScene, kScene}, false)[0];
  const auto r = static_cast<int64_t>(seed % 7) * kScene / 10, c = static_cast<int64_t>(seed % 5) * kScene / 8;
  X.narrow(1, r, kScene / 3).narrow(2, c, kScene / 4) += 0.5;
  return X;  // {4,N,N}
}

struct StructuredCamera {
  torch::Tensor P, Q;  // centred, {4,m,N} and {4,n,N}
  StructuredCamera() {
    auto gen = at::detail::createCPUGenerator(3);
    const auto length = [](int64_t m, double s) {
      return m + static_cast<int64_t>(std::ceil(std::abs(s) * static_cast<double>(kScene - 1))) + 2;
    };
    // A binary-ish code seen through the pixels: the profile's samples in {0.2, 1}.
    const auto code = [&](int64_t L) { return 0.2 + 0.8 * (at::rand({4, L}, gen) > 0.5).to(torch::kFloat64); };
    P = shift_factor(code(length(kRows, kShiftRows)), kRows, kScene, kShiftRows, 1.0);
    Q = shift_factor(code(length(kCols, kShiftCols)), kCols, kScene, kShiftCols, 1.0);
  }
  // The capture of scene X, and a "reconstruction" of it made with another normalisation: gain and
  // offset per channel, clipped at zero as an 8-bit file would be.
  ReferencePair pair(int i, double noise) const {
    const auto X = scene(100 + static_cast<uint64_t>(i));
    auto gen = at::detail::createCPUGenerator(200 + static_cast<uint64_t>(i));
    auto Y = torch::matmul(torch::matmul(P, X), Q.transpose(1, 2));
    Y = Y + noise * Y.std() * at::randn(Y.sizes(), gen).to(torch::kFloat64);
    Y = Y - Y.mean(1, true) - Y.mean(2, true) + Y.mean({1, 2}, true);  // double-centred, as captures are
    const auto gain = torch::tensor({0.8, 1.1, 1.0, 1.3}, torch::kFloat64).view({4, 1, 1}) * (1 + 0.2 * i);
    const auto reference = (gain * X - 0.1 * i).clamp_min(0);
    return {"pair" + std::to_string(i), Y.to(torch::kFloat32), reference.to(torch::kFloat32)};
  }
};

// The P-step's normal equations (G = sum Z Z^T, H = sum Y Z^T, Z = X Q^T) over three noise-free pairs
// of a camera with the true Q.
template <typename Camera>
std::pair<torch::Tensor, torch::Tensor> p_step_normal_equations(const Camera& camera) {
  torch::Tensor G, H;
  for (int i = 0; i < 3; ++i) {
    const auto p = camera.pair(i, 0.0);
    const auto Z = torch::matmul(scene(100 + static_cast<uint64_t>(i)), camera.Q.transpose(1, 2));
    const auto g = torch::matmul(Z, Z.transpose(1, 2)),
               h = torch::matmul(p.meas.to(torch::kFloat64), Z.transpose(1, 2));
    G = i == 0 ? g : G + g;
    H = i == 0 ? h : H + h;
  }
  return {G, H};
}

ReferenceCalibrationOptions quiet() {
  ReferenceCalibrationOptions o;
  o.progress = false;
  return o;
}

}  // namespace

TEST_CASE("the exact shift-profile solve reaches the least objective conjugate gradients approach",
          "[optics][calibrate]") {
  const StructuredCamera camera;
  const auto [G, H] = p_step_normal_equations(camera);
  ShiftFitOptions o;
  o.cg_tolerance = 1e-12;
  for (const double shift : {kShiftRows, 1.7}) {
    INFO("shift " << shift);
    const auto exact = solve_shift_factor(G, H, shift);
    const auto cg = fit_shift_factor(G, H, shift, o, 3000);
    CHECK(exact.factor.sizes() == torch::IntArrayRef({4, kRows, kScene}));
    // Never worse than CG, and equal to it where CG converged.
    CHECK((exact.objective <= cg.objective + 1e-9 * cg.objective.abs()).all().item<bool>());
    CHECK(((exact.objective - cg.objective).abs() <= 1e-3 * cg.objective.abs()).all().item<bool>());
  }
  // At the true shift the profile reproduces the camera's P (no noise): P X Q^T is matched exactly.
  const auto exact = solve_shift_factor(G, H, kShiftRows);
  CHECK(((exact.factor - camera.P).norm() / camera.P.norm()).item<double>() < 2e-3);
}

TEST_CASE("three captures and reconstructions of them identify a shift-structured camera, shifts included",
          "[optics][calibrate]") {
  const StructuredCamera camera;
  std::vector<ReferencePair> pairs;
  for (int i = 0; i < 4; ++i) pairs.push_back(camera.pair(i, 0.02));
  const std::vector<ReferencePair> three(pairs.begin(), pairs.begin() + 3);
  const auto fit = calibrate_from_references(three, quiet());
  CHECK(std::abs(fit.shift_rows - kShiftRows) < 0.01);
  CHECK(std::abs(fit.shift_cols - kShiftCols) < 0.01);
  for (const double r : fit.residual) CHECK(r < 0.1);
  // Each pair's gain comes back up to the mean gain's normalisation: reference 2 is 1.4 times as
  // bright as reference 0 in every channel, so its gain (reference to scene) is 1 / 1.4 of pair 0's.
  for (int c = 0; c < 4; ++c) CHECK(std::abs(fit.gain_offset[2][c] / fit.gain_offset[0][c] - 1 / 1.4) < 0.05);
  // Held out, each pair's Tikhonov follows its reference.
  // With the whole calibration given, each held-out fit's factors are measured against it: close
  // (the pairs agree) and not identical (each fit saw other pairs and other noise).
  const auto whole = calibrate_from_references(pairs, quiet());
  const auto held = leave_one_out(pairs, 1e-4, quiet(), &whole.calib);
  REQUIRE(held.size() == 4);
  for (const auto& h : held) {
    INFO(h.name);
    for (const double c : h.correlation) CHECK(c > 0.95);
    CHECK(std::abs(h.shift_rows - kShiftRows) < 0.02);
    CHECK(h.change_p > 1e-6);
    CHECK(h.change_p < 0.2);
    CHECK(h.change_q > 1e-6);
    CHECK(h.change_q < 0.2);
    CHECK(h.change_coded > 1e-6);
    CHECK(h.change_coded < 0.2);
  }
  CHECK(leave_one_out(three, 1e-4, quiet())[0].change_p < 0);  // not given: not measured (three pairs: cheaper)
}

TEST_CASE("reference calibration names a flat capture, a flat reference and too few pairs for leave-one-out",
          "[optics][calibrate][errors]") {
  const StructuredCamera camera;
  std::vector<ReferencePair> pairs = {camera.pair(0, 0.0), camera.pair(1, 0.0), camera.pair(2, 0.0)};
  auto dark = pairs;
  dark[1].meas = torch::zeros_like(dark[1].meas);
  CHECK_THROWS_WITH(calibrate_from_references(dark, quiet()), Contains("pair1") && Contains("no signal"));
  auto flat = pairs;
  flat[2].reference = torch::full_like(flat[2].reference, 0.5);
  CHECK_THROWS_WITH(calibrate_from_references(flat, quiet()), Contains("pair2") && Contains("flat"));
  auto nan = pairs;
  nan[0].meas[0][0][0] = NAN;
  CHECK_THROWS_WITH(calibrate_from_references(nan, quiet()), Contains("pair0") && Contains("NaN"));
  const std::vector<ReferencePair> two(pairs.begin(), pairs.begin() + 2);
  CHECK_THROWS_WITH(leave_one_out(two, 1e-4, quiet()), Contains("at least 3"));
}

namespace {

torch::Tensor double_centred(const torch::Tensor& Y) {
  return Y - Y.mean(1, true) - Y.mean(2, true) + Y.mean({1, 2}, true);
}

// How far the calibration's forward model of the true scene X is from the capture Y, relative.
double forward_error(const Calibration& calib, const torch::Tensor& X, const torch::Tensor& Y) {
  const auto model = double_centred(torch::matmul(torch::matmul(calib.P, X), calib.Q.transpose(1, 2)));
  return ((model - Y.to(torch::kFloat64)).norm() / Y.to(torch::kFloat64).norm()).item<double>();
}

}  // namespace

TEST_CASE("a white capture sets a reference calibration's light unit: the scene's light, not the references'",
          "[optics][calibrate]") {
  const StructuredCamera camera;
  // References stretched as a displayed picture is: 2 x (0.8-1.3) x (1 + 0.2 i) as bright as the scenes.
  std::vector<ReferencePair> pairs = {camera.pair(0, 0.02), camera.pair(1, 0.02), camera.pair(2, 0.02)};
  for (auto& p : pairs) p.reference = 2 * p.reference;
  auto fit = calibrate_from_references(pairs, quiet());
  const auto X0 = scene(100);
  // In the references' units the calibration does not explain the true scene's capture.
  const double before = forward_error(fit.calib, X0, pairs[0].meas);
  CHECK(before > 0.5);

  // A uniform scene of light 0.7 (eq. 2), with the sensor's noise.
  const double light = 0.7;
  auto gen = at::detail::createCPUGenerator(9);
  auto white = double_centred(torch::matmul(
      torch::matmul(camera.P, torch::full({4, kScene, kScene}, light, torch::kFloat64)), camera.Q.transpose(1, 2)));
  white = white + 0.01 * white.std() * at::randn(white.sizes(), gen).to(torch::kFloat64);
  const auto frame = fit_white_frame(white.to(torch::kFloat32), fit.calib, 3e-4);
  std::array<double, 4> scale{};
  for (size_t c = 0; c < 4; ++c) {
    CHECK(frame.residual[c] < 0.1);
    scale[c] = light / frame.level[c];
  }
  const auto rows_before = fit.profile_rows.clone(), cols_before = fit.profile_cols.clone();
  rescale_scene_units(fit, scale);
  INFO("forward error before " << before);
  CHECK(forward_error(fit.calib, X0, pairs[0].meas) < 0.1);
  for (size_t c = 0; c < 4; ++c) {
    INFO("channel " << c);
    // The pairs' scenes, a R + b, are now the true scenes' light.
    const double truth = X0[static_cast<int64_t>(c)].mean().item<double>();
    CHECK(std::abs(fit.scene_means[0][c] / truth - 1) < 0.1);
  }
  // The profiles (what --compact writes) move with the factors.
  for (size_t c = 0; c < 4; ++c) {
    const auto k = 1 / std::sqrt(scale[c]);
    const auto i = static_cast<int64_t>(c);
    CHECK(torch::allclose(fit.profile_rows[i], rows_before[i] * k));
    CHECK(torch::allclose(fit.profile_cols[i], cols_before[i] * k));
  }

  // A capture of a scene is no white frame: a uniform scene leaves most of its coded light.
  const auto scene_frame = fit_white_frame(camera.pair(3, 0.0).meas, fit.calib, 3e-4);
  CHECK(*std::max_element(scene_frame.residual.begin(), scene_frame.residual.end()) > 0.5);
  CHECK_THROWS_WITH(fit_white_frame(torch::zeros({4, kRows + 1, kCols}), fit.calib, 3e-4), Contains("window"));
  CHECK_THROWS_WITH(rescale_scene_units(fit, {1, 1, 0, 1}), Contains("positive"));
}

TEST_CASE("without a white capture, a prior on the scenes sets the light unit: one scale, the colour kept",
          "[optics][calibrate]") {
  const StructuredCamera camera;
  std::vector<ReferencePair> pairs = {camera.pair(0, 0.02), camera.pair(1, 0.02), camera.pair(2, 0.02)};
  for (auto& p : pairs) p.reference = 2.5 * p.reference;  // stretched: 2.5 x the scenes' light
  auto fit = calibrate_from_references(pairs, quiet());
  const auto geometric_mean = [&] {
    double log_sum = 0;
    for (const auto& m : fit.scene_means) log_sum += std::log((m[0] + m[1] + m[2] + m[3]) / 4);
    return std::exp(log_sum / static_cast<double>(fit.scene_means.size()));
  };
  std::vector<double> balance;  // each pair's blue against its red, in the references' units
  for (const auto& m : fit.scene_means) balance.push_back(m[0] / m[3]);
  const double before = geometric_mean();
  const double scale = typical_scene_scale(fit, 0.063);
  CHECK(scale == Approx(0.063 / before).epsilon(1e-12));
  const Calibration in_references_units{fit.calib.P.clone(), fit.calib.Q.clone()};
  rescale_scene_units(fit, {scale, scale, scale, scale});
  CHECK(geometric_mean() == Approx(0.063).epsilon(1e-9));
  for (size_t i = 0; i < fit.scene_means.size(); ++i)
    CHECK(fit.scene_means[i][0] / fit.scene_means[i][3] == Approx(balance[i]).epsilon(1e-9));
  // The same captures: a scene `scale` times brighter in the new unit through factors that carry the
  // inverse of the scale.
  const auto X0 = scene(100);
  const auto coded = [](const Calibration& c, const torch::Tensor& X) {
    return torch::matmul(torch::matmul(c.P, X), c.Q.transpose(1, 2));
  };
  CHECK(torch::allclose(coded(fit.calib, X0 * scale), coded(in_references_units, X0), 1e-9, 1e-12));
  CHECK_FALSE(torch::allclose(coded(fit.calib, X0), coded(in_references_units, X0), 1e-3, 0));
  // No prior without scenes of positive light; a light that is not one is refused.
  auto dark = fit;
  dark.scene_means[1] = {0, 0, 0, 0};
  CHECK(typical_scene_scale(dark, 0.063) == 0);
  CHECK_THROWS_WITH(typical_scene_scale(fit, 0), Contains("positive"));
  CHECK_THROWS_WITH(typical_scene_scale(fit, std::nan("")), Contains("positive"));
}

namespace {

// A fixed flare on the sensor {4,m,n}, double-centred as the planes are: a wide off-centre glow, a
// ripple on it and a thin diagonal streak (issue 111's twin), `share` of the captures' coded norm.
torch::Tensor fixed_flare(const torch::Tensor& like, double share) {
  const auto rows = torch::arange(kRows, torch::kFloat64).view({-1, 1}) / kRows;
  const auto cols = torch::arange(kCols, torch::kFloat64).view({1, -1}) / kCols;
  const auto glow = torch::exp(-((rows - 0.3).square() + (cols - 0.7).square()) / 0.1);
  const auto ripple = 0.3 * glow * torch::cos(2 * M_PI * (rows * 9 + cols * 6));
  const auto streak = 0.5 * torch::exp(-(rows - 0.8 * cols - 0.1).square() / 2e-4);
  auto F = (glow + ripple + streak).unsqueeze(0).repeat({4, 1, 1}) *
           torch::tensor({0.9, 1.0, 1.1, 1.2}, torch::kFloat64).view({4, 1, 1});
  F = double_centred(F);
  return F * (share * like.to(torch::kFloat64).norm() / F.norm());
}

}  // namespace

TEST_CASE(
    "a light every capture holds is fitted as its own term: the factors, the held-out pairs and the "
    "classical reconstruction stay the flare-free ones",
    "[optics][calibrate]") {
  const StructuredCamera camera;
  std::vector<ReferencePair> pairs;
  for (int i = 0; i < 4; ++i) pairs.push_back(camera.pair(i, 0.01));
  // The flare is as strong as half the coded light: fitted without its term, it is most of the residual.
  const auto F = fixed_flare(pairs[0].meas, 0.5);
  for (auto& p : pairs) p.meas = (p.meas.to(torch::kFloat64) + F).to(torch::kFloat32);
  auto with = quiet();
  with.fixed_light = true;
  const auto ignored = calibrate_from_references(pairs, quiet());  // off by default
  const auto fitted = calibrate_from_references(pairs, with);
  REQUIRE(fitted.calib.fixed_light.defined());
  CHECK_FALSE(ignored.calib.fixed_light.defined());
  for (size_t c = 0; c < 4; ++c) {
    INFO("channel " << c);
    CHECK(ignored.residual[c] > 0.2);
    CHECK(fitted.residual[c] < 0.1);
  }
  CHECK(std::abs(fitted.shift_rows - kShiftRows) < 0.01);
  CHECK(std::abs(fitted.shift_cols - kShiftCols) < 0.01);
  // The flare comes back, up to what a uniform scene's shadow holds (the gauge: F _|_ U).
  const auto U = torch::matmul(fitted.calib.P.sum(2, true), fitted.calib.Q.sum(2, true).transpose(1, 2));
  const auto along_U = (F * U).sum({1, 2}, true) / U.square().sum({1, 2}, true);
  CHECK(((fitted.calib.fixed_light - (F - along_U * U)).norm() / F.norm()).item<double>() < 0.1);
  // Each factor is the true one (up to its scale): the flare is not in the profiles.
  const auto cosine = [](const torch::Tensor& a, const torch::Tensor& b) {
    return ((a * b).sum() / (a.norm() * b.norm())).abs().item<double>();
  };
  for (int64_t c = 0; c < 4; ++c) {
    CHECK(cosine(fitted.calib.P[c], camera.P[c]) > 0.99);
    CHECK(cosine(fitted.calib.Q[c], camera.Q[c]) > 0.99);
    CHECK(cosine(ignored.calib.P[c], camera.P[c]) < cosine(fitted.calib.P[c], camera.P[c]));
  }
  // Held out, each pair's capture less the others' fixed light follows its reference.
  for (const auto& h : leave_one_out(pairs, 1e-4, with)) {
    INFO(h.name);
    for (const double r : h.correlation) CHECK(r > 0.95);
  }
  // Tikhonov through the calibration subtracts its fixed light: the flared capture reconstructs as
  // the flare-free one does.
  CameraConfig cam;
  cam.raw.crop = {0, 0, kRows, kCols};
  cam.raw.centring = Centring::none;
  cam.scene_size = kScene;
  cam.display_gamma = 1;
  auto flare_free = fitted.calib;
  flare_free.fixed_light = torch::Tensor();
  const auto flared = pairs[3].meas.unsqueeze(0);
  const auto clean = (pairs[3].meas.to(torch::kFloat64) - fitted.calib.fixed_light).to(torch::kFloat32).unsqueeze(0);
  ClassicalOptions tikhonov;
  tikhonov.lambda = 1e-4;
  const auto through_fixed = make_classical(fitted.calib, cam, tikhonov)->reconstruct(flared);
  const auto through_free = make_classical(flare_free, cam, tikhonov)->reconstruct(clean);
  CHECK(torch::allclose(through_fixed, through_free, 1e-4, 1e-5));
  CHECK_FALSE(
      torch::allclose(make_classical(flare_free, cam, tikhonov)->reconstruct(flared), through_free, 1e-2, 1e-3));
}

TEST_CASE("a calibration's fixed light is written with it and read back, and a partial or wrong-sized one is named",
          "[optics][calibrate][io]") {
  const StructuredCamera camera;
  CameraConfig cam;
  cam.raw.crop = {0, 0, kRows, kCols};
  cam.scene_size = kScene;
  const auto dir = std::filesystem::temp_directory_path() / ("flatnet_fixed_light_" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  Calibration calib{camera.P, camera.Q, fixed_flare(camera.pair(0, 0.0).meas, 0.3)};
  save_calibration(dir / "full.mat", calib);
  const auto back = load_calibration(dir / "full.mat", cam);
  REQUIRE(back.fixed_light.defined());
  CHECK(torch::allclose(back.fixed_light, calib.fixed_light));
  // Without one, none.
  save_calibration(dir / "none.mat", Calibration{camera.P, camera.Q});
  CHECK_FALSE(load_calibration(dir / "none.mat", cam).fixed_light.defined());
  // A calibration simulated through carries it on every capture (calibration_rig).
  cam.noise_gain = 1e-5;
  cam.open_light = 1;
  cam.raw.raw_height = 2 * kRows;
  cam.raw.raw_width = 2 * kCols;
  const auto rig = calibration_rig(back, cam);
  REQUIRE(rig.fixed_light.defined());
  const auto dark_scene = torch::zeros({1, 4, kScene, kScene});
  CHECK(torch::allclose(expected_signal(rig, dark_scene)[0].narrow(1, 0, kRows).narrow(2, 0, kCols),
                        calib.fixed_light.to(torch::kFloat32), 1e-5, 1e-6));
  // Three planes of four, and a plane of the wrong size, are named.
  std::map<std::string, torch::Tensor> vars;
  for (int c = 0; c < 4; ++c) {
    vars[std::string("P1") + kChannelNames[c]] = camera.P[c];
    vars[std::string("Q1") + kChannelNames[c]] = camera.Q[c];
  }
  for (int c = 0; c < 3; ++c) vars[std::string("fixed_light_") + kChannelNames[c]] = calib.fixed_light[c];
  write_mat(dir / "partial.mat", vars);
  CHECK_THROWS_WITH(load_calibration(dir / "partial.mat", cam), Contains("partial.mat") && Contains("all four"));
  vars["fixed_light_r"] = torch::zeros({kRows, kCols + 1}, torch::kFloat64);
  write_mat(dir / "wrong.mat", vars);
  CHECK_THROWS_WITH(load_calibration(dir / "wrong.mat", cam), Contains("wrong.mat") && Contains("fixed_light_r"));
  std::filesystem::remove_all(dir);
}

namespace {

// A camera whose four planes see one mask per axis (shift_structure.hpp eq. 3): each plane's profile
// is the mask's through a kernel of its own. b: the mask itself; gb: half a pixel on; gr: blurred;
// r: half a pixel back, at 1.2 times the gain.
struct OneMaskCamera {
  torch::Tensor P, Q;                                 // centred, {4,m,N} and {4,n,N}
  torch::Tensor mask_rows, mask_cols;                 // {L}
  static torch::Tensor kernels() {                    // {4,5}, taps at -2..2
    return torch::tensor({0.0, 0.0,  1.0, 0.0,  0.0,  //
                          0.0, 0.0,  0.5, 0.5,  0.0,  //
                          0.0, 0.25, 0.5, 0.25, 0.0,  //
                          0.0, 0.6,  0.6, 0.0,  0.0},
                         torch::kFloat64)
        .view({4, 5});
  }
  // f_c[t] = sum_a k_c[a] m[t - (a - 2)], zero beyond the ends.
  static torch::Tensor through_kernels(const torch::Tensor& mask) {
    const auto k = kernels();
    const int64_t L = mask.size(0);
    const auto padded = torch::constant_pad_nd(mask, {2, 2});
    auto f = torch::zeros({4, L}, torch::kFloat64);
    for (int64_t a = 0; a < 5; ++a) f += k.select(1, a).view({4, 1}) * padded.narrow(0, 4 - a, L).view({1, L});
    return f;
  }
  OneMaskCamera() {
    auto gen = at::detail::createCPUGenerator(5);
    const auto length = [](int64_t m, double s) {
      return m + static_cast<int64_t>(std::ceil(std::abs(s) * static_cast<double>(kScene - 1))) + 2;
    };
    const auto code = [&](int64_t L) { return 0.2 + 0.8 * (at::rand({L}, gen) > 0.5).to(torch::kFloat64); };
    mask_rows = code(length(kRows, kShiftRows));
    mask_cols = code(length(kCols, kShiftCols));
    P = shift_factor(through_kernels(mask_rows), kRows, kScene, kShiftRows, 1.0);
    Q = shift_factor(through_kernels(mask_cols), kCols, kScene, kShiftCols, 1.0);
  }
  ReferencePair pair(int i, double noise) const {
    StructuredCamera as;  // the same captures and references, through this camera's factors
    as.P = P;
    as.Q = Q;
    return as.pair(i, noise);
  }
};

double cosine(const torch::Tensor& a, const torch::Tensor& b) {
  return ((a * b).sum() / (a.norm() * b.norm())).abs().item<double>();
}

}  // namespace

TEST_CASE("one mask through a kernel per plane: the exact solve recovers the mask, the planes' kernels and P",
          "[optics][calibrate]") {
  const OneMaskCamera camera;
  const auto [G, H] = p_step_normal_equations(camera);
  auto impulse = torch::zeros({4, 5}, torch::kFloat64);
  impulse.select(1, 2).fill_(1.0);
  const auto shared = solve_shared_shift_factor(G, H, kShiftRows, impulse, 20);
  REQUIRE(shared.kernels.sizes() == torch::IntArrayRef({4, 5}));
  REQUIRE(shared.mask.size(0) == shift_profile_length(kRows, kScene, kShiftRows, 1.0));
  // The least objective free profiles reach is reached with one mask (the camera is one).
  const auto free = solve_shift_factor(G, H, kShiftRows);
  CHECK((shared.fit.objective <= free.objective + 1e-3 * free.objective.abs()).all().item<bool>());
  for (int64_t c = 0; c < 4; ++c) {
    INFO("channel " << c);
    CHECK(cosine(shared.fit.factor[c], camera.P[c]) > 0.999);
  }
  // The kernels come back up to the gauge (a common scale and sub-pixel shift): the offsets between
  // the planes' centroids and the blur of gr against b.
  const auto centroid = [&](int64_t c) {
    const auto k = shared.kernels[c];
    return ((torch::arange(5, torch::kFloat64) - 2) * k).sum().item<double>() / k.sum().item<double>();
  };
  CHECK(std::abs((centroid(1) - centroid(0)) - 0.5) < 0.05);
  CHECK(std::abs((centroid(3) - centroid(0)) + 0.5) < 0.05);
  CHECK(std::abs(shared.kernels[3].sum().item<double>() / shared.kernels[0].sum().item<double>() - 1.2) < 0.02);
  // A channel's sign is its own (P_c and Q_c may both change sign): a kernel of one sign, the other's.
  auto flipped = H.clone();
  flipped[2] *= -1;
  const auto signed_fit = solve_shared_shift_factor(G, flipped, kShiftRows, impulse, 20);
  CHECK(signed_fit.kernels[2].sum().item<double>() < 0);
  CHECK(signed_fit.kernels[0].sum().item<double>() > 0);
  for (int64_t c = 0; c < 4; ++c) CHECK(cosine(signed_fit.fit.factor[c], camera.P[c]) > 0.999);
  // Kernels of an even width have no centre: refused.
  CHECK_THROWS_WITH(solve_shared_shift_factor(G, H, kShiftRows, torch::ones({4, 4}, torch::kFloat64), 1),
                    Contains("odd kernel"));
}

TEST_CASE("a shared mask fits noisy captures closer to the true factors than a profile per plane",
          "[optics][calibrate]") {
  const OneMaskCamera camera;
  std::vector<ReferencePair> pairs;
  // Noisy: each plane's own profile would fit its own noise.
  for (int i = 0; i < 4; ++i) pairs.push_back(camera.pair(i, 0.3));
  auto shared_options = quiet();
  shared_options.shared_mask = true;
  const auto per_plane = calibrate_from_references(pairs, quiet());
  const auto shared = calibrate_from_references(pairs, shared_options);
  REQUIRE(shared.kernels_rows.defined());
  CHECK_FALSE(per_plane.kernels_rows.defined());
  CHECK(std::abs(shared.shift_rows - kShiftRows) < 0.01);
  CHECK(std::abs(shared.shift_cols - kShiftCols) < 0.01);
  double gain_p = 0, gain_q = 0;
  for (int64_t c = 0; c < 4; ++c) {
    INFO("channel " << c);
    const double shared_p = cosine(shared.calib.P[c], camera.P[c]), free_p = cosine(per_plane.calib.P[c], camera.P[c]);
    const double shared_q = cosine(shared.calib.Q[c], camera.Q[c]), free_q = cosine(per_plane.calib.Q[c], camera.Q[c]);
    CHECK(shared_p > 0.95);
    CHECK(shared_q > 0.95);
    gain_p += shared_p - free_p;
    gain_q += shared_q - free_q;
  }
  CHECK(gain_p > 0);
  CHECK(gain_q > 0);
  // The camera file's line names each plane's offset.
  const auto line = describe_shared_mask(shared);
  CHECK_THAT(line, Contains("one mask per axis"));
  CHECK_THAT(line, Contains("rows:"));
  CHECK(describe_shared_mask(per_plane).empty());
  auto bad = shared_options;
  bad.mask_taps = 4;
  CHECK_THROWS_WITH(calibrate_from_references(pairs, bad), Contains("odd number of taps"));
}

namespace {

// Pair i's capture as calibrate's noise model samples it: the planes, a level, nothing saturated.
std::vector<NoiseSample> samples_of(const std::vector<ReferencePair>& pairs) {
  std::vector<NoiseSample> samples;
  for (const auto& p : pairs) samples.push_back({p.meas, torch::full({4}, 0.2, torch::kFloat64), 0.0});
  return samples;
}

CameraConfig small_geometry() {
  CameraConfig geometry;
  geometry.scene_size = kScene;
  return geometry;
}

}  // namespace

TEST_CASE("the reference calibration procedure: held-out check, light unit and camera keys without the CLI",
          "[optics][calibrate]") {
  const StructuredCamera camera;
  std::vector<ReferencePair> pairs;
  for (int i = 0; i < 4; ++i) pairs.push_back(camera.pair(i, 0.02));
  ReferenceCameraOptions o;
  o.fit = quiet();

  SECTION("four pairs, no white capture: checked on held-out pairs, the scenes' prior sets the unit") {
    const auto cam = identify_reference_camera(pairs, samples_of(pairs), std::nullopt, small_geometry(), o);
    REQUIRE(cam.held.size() == 4);
    CHECK(cam.held_mean > 0.95);
    CHECK(cam.held_change > 0);
    CHECK(cam.held_change < 0.5);
    CHECK(cam.light.source == LightUnitSource::scene_prior);
    CHECK(cam.light.light == kTypicalSceneLight);
    // After the unit: the pairs' scenes hold the prior's light on average (geometric mean over pairs).
    double log_sum = 0;
    for (const auto& m : cam.fit.scene_means) log_sum += std::log((m[0] + m[1] + m[2] + m[3]) / 4);
    CHECK(std::exp(log_sum / 4) == Approx(kTypicalSceneLight).epsilon(1e-9));
    // The camera's regulariser is the relative one made absolute through the final calibration.
    CHECK(cam.camera.tikhonov_lambda ==
          Approx(absolute_tikhonov_lambda(separable_inverse(cam.fit.calib.P, cam.fit.calib.Q, 1.0), o.lambda)));
    CHECK(cam.camera.scene_size == kScene);
    const auto header = reference_camera_header(cam);
    CHECK_THAT(header, Contains("from 4 captures") && Contains("mean held-out correlation") &&
                           Contains("taken to hold 0.063") && Contains("tikhonov_lambda is 0.0003"));
    CHECK(cam.fixed_light_share < 0);
  }

  SECTION("two pairs and --scene-light 0: no held-out check, the references' units kept") {
    o.scene_light = 0;
    const std::vector<ReferencePair> two(pairs.begin(), pairs.begin() + 2);
    const auto cam = identify_reference_camera(two, samples_of(two), std::nullopt, small_geometry(), o);
    CHECK(cam.held.empty());
    CHECK(cam.held_mean < 0);
    CHECK(cam.light.source == LightUnitSource::references);
    const auto header = reference_camera_header(cam);
    CHECK_THAT(header, !Contains("leave-one-out") && !Contains("scene light"));
  }

  SECTION("a white capture measures the unit: the scenes come back in their true light") {
    const std::vector<ReferencePair> three(pairs.begin(), pairs.begin() + 3);
    const double light = 0.7;
    const auto white = double_centred(torch::matmul(
        torch::matmul(camera.P, torch::full({4, kScene, kScene}, light, torch::kFloat64)), camera.Q.transpose(1, 2)));
    const WhiteCaptureInput input{"/captures/white.png", light, {white.to(torch::kFloat32), torch::full({4}, 0.5), 0}};
    const auto cam = identify_reference_camera(three, samples_of(three), input, small_geometry(), o);
    CHECK(cam.light.source == LightUnitSource::white_capture);
    CHECK(cam.light.white_residual < 0.1);
    const double truth = scene(100)[0].mean().item<double>();
    CHECK(std::abs(cam.fit.scene_means[0][0] / truth - 1) < 0.1);
    CHECK_THAT(reference_camera_header(cam), Contains("from the white capture white.png (light 0.7)"));
  }

  SECTION("ranges and a saturated white are refused before any fit, naming the flag or the file") {
    auto bad = o;
    bad.lambda = 1.5;
    CHECK_THROWS_WITH(identify_reference_camera(pairs, samples_of(pairs), std::nullopt, small_geometry(), bad),
                      Contains("--reference-lambda"));
    bad = o;
    bad.fit.shift.max_shift = 40;
    CHECK_THROWS_WITH(identify_reference_camera(pairs, samples_of(pairs), std::nullopt, small_geometry(), bad),
                      Contains("--min-shift"));
    const WhiteCaptureInput saturated{"white.png", 1, {pairs[0].meas, torch::full({4}, 0.9), 0.02}};
    CHECK_THROWS_WITH(identify_reference_camera(pairs, samples_of(pairs), saturated, small_geometry(), o),
                      Contains("white.png") && Contains("is saturated (2"));
    CHECK_THROWS_WITH(identify_reference_camera(pairs, samples_of({pairs[0]}), std::nullopt, small_geometry(), o),
                      Contains("one capture sample per pair"));
  }
}
