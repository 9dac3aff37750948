// The calibration identified from display-capture pairs (optics/calibrate_dataset): on a small
// camera with a known response, alternating least squares recovers P and Q up to their scale split,
// through noise and the open part's rank-1 light, and streams pairs it cannot cache. Random factors
// have no shift structure, so those cases fit free factors; a FlatCam-like camera (each factor's
// columns one profile moved by a shift) is identified with the structure, shift included, from pairs
// too noisy for the free fit.
#include <cmath>

#include "catch_torch.hpp"

#include "core/error.hpp"
#include "optics/calibrate.hpp"
#include "optics/calibrate_dataset.hpp"
#include "optics/shift_structure.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

constexpr int64_t kRows = 20, kCols = 24, kScene = 8;

// A camera Y = P X Q^T + s a b^T (+ noise), double-centred as captures are.
struct SmallCamera {
  torch::Tensor P, Q, a, b;
  explicit SmallCamera(uint64_t seed) {
    auto gen = at::detail::createCPUGenerator(seed);
    auto centre = [](const torch::Tensor& t) { return t - t.mean(1, true); };  // zero-mean columns
    P = centre(at::randn({4, kRows, kScene}, gen).to(torch::kFloat64));
    Q = centre(at::randn({4, kCols, kScene}, gen).to(torch::kFloat64));
    a = centre(at::randn({4, kRows, 1}, gen).to(torch::kFloat64)).squeeze(2) * 0.05;
    b = centre(at::randn({4, kCols, 1}, gen).to(torch::kFloat64)).squeeze(2) * 0.05;
  }
  CapturePair capture(int64_t i, double noise) const {
    auto gen = at::detail::createCPUGenerator(1000 + static_cast<uint64_t>(i));
    // Smooth-ish positive scenes, as photographs are: a random field blurred by a 2x2 mean.
    auto X = at::rand({4, kScene + 1, kScene + 1}, gen).to(torch::kFloat64);
    X = 0.25 * (X.narrow(1, 0, kScene).narrow(2, 0, kScene) + X.narrow(1, 1, kScene).narrow(2, 0, kScene) +
                X.narrow(1, 0, kScene).narrow(2, 1, kScene) + X.narrow(1, 1, kScene).narrow(2, 1, kScene));
    const auto s = X.sum({1, 2}).view({4, 1, 1});
    auto Y = torch::matmul(torch::matmul(P, X), Q.transpose(1, 2)) + s * torch::einsum("cr,cw->crw", {a, b});
    Y = Y + noise * at::randn(Y.sizes(), gen).to(torch::kFloat64);
    return {Y.to(torch::kFloat32), X.to(torch::kFloat32), {}};
  }
};

}  // namespace

TEST_CASE("alternating least squares identifies P and Q from display-capture pairs", "[optics][calibrate]") {
  const SmallCamera camera(7);
  DatasetCalibrationOptions o;
  o.progress = false;
  o.structure = FactorStructure::Free;
  o.iterations = 30;
  o.tolerance = 1e-9;
  for (const double noise : {0.0, 0.05}) {
    INFO("noise " << noise);
    const auto fit = calibrate_from_pairs(
        300, [&](int64_t i) { return camera.capture(i, noise); }, kRows, kCols, kScene, o);
    CHECK(fit.calib.P.sizes() == torch::IntArrayRef({4, kRows, kScene}));
    CHECK(fit.calib.Q.sizes() == torch::IntArrayRef({4, kCols, kScene}));
    const auto err = calibration_error(fit.calib, {camera.P, camera.Q});
    CHECK(err.forward < (noise == 0 ? 1e-4 : 0.03));
    CHECK(err.p < (noise == 0 ? 1e-4 : 0.03));
    CHECK(fit.iterations < 30);  // converged before the cap
    // The residual is what the noise leaves: none, or about its share of the capture's energy.
    for (const double r : fit.residual) CHECK(r < (noise == 0 ? 1e-3 : 0.2));
    // The response to a uniform scene: the coded part's mean plus the open part's rank-1 light.
    const auto ones = torch::ones({4, kScene, 1}, torch::kFloat64);
    const auto m_true = torch::matmul(torch::matmul(camera.P, ones), torch::matmul(camera.Q, ones).transpose(1, 2)) /
                            static_cast<double>(kScene * kScene) +
                        torch::einsum("cr,cw->crw", {camera.a, camera.b});
    const auto m_fit = fit.uniform_response.to(torch::kFloat64);
    CHECK(((m_fit - m_true).norm() / m_true.norm()).item<double>() < (noise == 0 ? 1e-3 : 0.05));
  }
}

TEST_CASE("pairs beyond the memory budget are re-read, with the same answer", "[optics][calibrate]") {
  const SmallCamera camera(3);
  DatasetCalibrationOptions o;
  o.progress = false;
  o.structure = FactorStructure::Free;
  o.iterations = 5;
  int64_t loads = 0;
  auto load = [&](int64_t i) {
    ++loads;
    return camera.capture(i, 0.01);
  };
  const auto cached = calibrate_from_pairs(40, load, kRows, kCols, kScene, o);
  const auto cached_loads = loads;
  CHECK(cached_loads == 40);  // decoded once
  loads = 0;
  o.cache_bytes = 0;
  const auto streamed = calibrate_from_pairs(40, load, kRows, kCols, kScene, o);
  CHECK(loads > 40 * 5);  // read again in every pass
  CHECK(torch::allclose(streamed.calib.P, cached.calib.P, 1e-5, 1e-6));
}

TEST_CASE("a pair of the wrong size or with NaN is named", "[optics][calibrate]") {
  const SmallCamera camera(1);
  DatasetCalibrationOptions o;
  o.progress = false;
  auto wrong = [&](int64_t i) {
    auto p = camera.capture(i, 0);
    if (i == 3) p.meas = p.meas.narrow(1, 0, kRows - 1);
    return p;
  };
  CHECK_THROWS_WITH(calibrate_from_pairs(5, wrong, kRows, kCols, kScene, o),
                    Contains("pair 3") && Contains("{4,20,24}"));
  auto nan = [&](int64_t i) {
    auto p = camera.capture(i, 0);
    if (i == 2) p.scene[0][0][0].fill_(NAN);
    return p;
  };
  CHECK_THROWS_WITH(calibrate_from_pairs(5, nan, kRows, kCols, kScene, o), Contains("pair 2") && Contains("NaN"));
}

namespace {

// A FlatCam-like camera: P[i,j] = f(i + j shift), Q likewise (optics/shift_structure.hpp), f a
// +-1 code seen through a 2-pixel blur, columns centred as captures are.
constexpr int64_t kShiftRows = 48, kShiftCols = 56, kShiftScene = 16;
constexpr double kShiftP = -1.7, kShiftQ = -1.45;

torch::Tensor coded_factor(int64_t rows, double shift, uint64_t seed) {
  auto gen = at::detail::createCPUGenerator(seed);
  const int64_t length = rows + static_cast<int64_t>(std::ceil(std::abs(shift) * kShiftScene)) + 4;
  auto code = (at::rand({4, length}, gen) < 0.5).to(torch::kFloat64) * 2 - 1;
  code = 0.25 * code.roll(1, 1) + 0.5 * code + 0.25 * code.roll(-1, 1);
  return shift_factor(code, rows, kShiftScene, shift, 1.0);
}

CapturePair coded_capture(const torch::Tensor& P, const torch::Tensor& Q, int64_t i, double noise) {
  auto gen = at::detail::createCPUGenerator(5000 + static_cast<uint64_t>(i));
  const int64_t n = kShiftScene;
  auto X = at::rand({4, n + 1, n + 1}, gen).to(torch::kFloat64);
  X = 0.25 * (X.narrow(1, 0, n).narrow(2, 0, n) + X.narrow(1, 1, n).narrow(2, 0, n) +
              X.narrow(1, 0, n).narrow(2, 1, n) + X.narrow(1, 1, n).narrow(2, 1, n));
  auto Y = torch::matmul(torch::matmul(P, X), Q.transpose(1, 2));
  Y = Y + noise * Y.std().item<double>() * at::randn(Y.sizes(), gen).to(torch::kFloat64);
  return {Y.to(torch::kFloat32), X.to(torch::kFloat32), {}};
}

}  // namespace

TEST_CASE("a FlatCam's factors and shifts are identified from pairs too noisy for free factors",
          "[optics][calibrate]") {
  const auto P = coded_factor(kShiftRows, kShiftP, 11), Q = coded_factor(kShiftCols, kShiftQ, 12);
  const double noise = 1.0;  // the noise as strong as the signal (docs/own-camera.md's random-code camera: 7 to 1)
  const auto load = [&](int64_t i) { return coded_capture(P, Q, i, noise); };
  DatasetCalibrationOptions o;
  o.progress = false;
  o.iterations = 12;
  const auto shaped = calibrate_from_pairs(60, load, kShiftRows, kShiftCols, kShiftScene, o);
  CHECK_FALSE(shaped.structure_rejected);
  CHECK(shaped.structure_explains > 0.3);
  CHECK(shaped.shift_rows == Approx(kShiftP).margin(1e-2));  // 0.16 pixel over the 16 columns
  CHECK(shaped.shift_cols == Approx(kShiftQ).margin(1e-2));  // 0.16 pixel over the 16 columns
  const auto shaped_err = calibration_error(shaped.calib, {P, Q});
  o.structure = FactorStructure::Free;
  const auto free = calibrate_from_pairs(60, load, kShiftRows, kShiftCols, kShiftScene, o);
  CHECK(free.shift_rows == 0);
  const auto free_err = calibration_error(free.calib, {P, Q});
  INFO("forward error: shift structure " << shaped_err.forward << ", free " << free_err.forward);
  CHECK(shaped_err.forward < 0.15);
  CHECK(shaped_err.forward < 0.5 * free_err.forward);
}

// Issue 94: a bench camera whose column window sits elsewhere along its code, with a second, weaker
// term, from 40 pairs twice as noisy as their signal. The structure used to be judged at its first
// step, with Q still free, and was rejected here (0.14 of the free share): both shifts were lost.
// Judged once both factors are structured, it is kept and both shifts are found.
TEST_CASE("a moving shadow is kept and both shifts found when its column window sits elsewhere on its code",
          "[optics][calibrate]") {
  const auto code = [](int64_t rows, double shift, uint64_t seed, int64_t skip) {
    auto gen = at::detail::createCPUGenerator(seed);
    const int64_t length = rows + static_cast<int64_t>(std::ceil(std::abs(shift) * kShiftScene)) + 4;
    auto c = ((at::rand({4, length + skip}, gen) < 0.5).to(torch::kFloat64) * 2 - 1).narrow(1, skip, length);
    c = 0.25 * c.roll(1, 1) + 0.5 * c + 0.25 * c.roll(-1, 1);
    return shift_factor(c, rows, kShiftScene, shift, 1.0);
  };
  // The column window 7 features further along the same code; the ghost term from other codes.
  const auto P = code(kShiftRows, kShiftP, 11, 0), Q = code(kShiftCols, kShiftQ, 12, 7);
  const auto P2 = code(kShiftRows, kShiftP, 21, 0), Q2 = code(kShiftCols, kShiftQ, 22, 0);
  const auto load = [&](int64_t i) {
    auto pair = coded_capture(P, Q, i, 2.0);
    const auto X = pair.scene.to(torch::kFloat64);
    pair.meas += (0.3 * torch::matmul(torch::matmul(P2, X), Q2.transpose(1, 2))).to(torch::kFloat32);
    return pair;
  };
  DatasetCalibrationOptions o;
  o.progress = false;
  o.iterations = 12;
  const auto fit = calibrate_from_pairs(40, load, kShiftRows, kShiftCols, kShiftScene, o);
  CHECK_FALSE(fit.structure_rejected);
  CHECK(fit.structure_explains > 0.3);
  CHECK(fit.shift_rows == Approx(kShiftP).margin(0.02));
  CHECK(fit.shift_cols == Approx(kShiftQ).margin(0.02));
  for (const double share : fit.axis_explains) CHECK(share > 0.3);  // each axis borne out
  // The same pairs from a camera with no moving shadow (random factors) are still refused it.
  auto gen = at::detail::createCPUGenerator(5);
  auto R = at::randn({4, kShiftRows, kShiftScene}, gen).to(torch::kFloat64),
       S = at::randn({4, kShiftCols, kShiftScene}, gen).to(torch::kFloat64);
  R -= R.mean(1, true);
  S -= S.mean(1, true);
  const auto random = calibrate_from_pairs(
      40, [&](int64_t i) { return coded_capture(R, S, i, 2.0); }, kShiftRows, kShiftCols, kShiftScene, o);
  CHECK(random.structure_rejected);
  CHECK(random.structure_explains < 0.3);
  CHECK(random.shift_rows == 0);
}

TEST_CASE("a factor with the shift structure is recovered exactly, and the shift is found on both signs",
          "[optics][calibrate]") {
  for (const double shift : {-2.3, 1.3}) {
    INFO("shift " << shift);
    const auto P = coded_factor(kShiftRows, shift, 3);  // {4,m,N}
    const auto G = torch::eye(kShiftScene, torch::kFloat64).expand({4, kShiftScene, kShiftScene});
    ShiftFitOptions o;
    // With G = I and H = P, J = ||F - P||^2 - ||P||^2: the fit is P's projection on the structure.
    const auto fit = fit_shift_factor(G, P, shift, o, 2000);
    CHECK(((fit.factor - P).norm() / P.norm()).item<double>() < 1e-6);
    CHECK(search_shift(G.narrow(0, 0, 1), P.narrow(0, 0, 1), o) == Approx(shift).margin(1e-3));
  }
  // A shift of 0 has no structure to fit.
  const auto G = torch::eye(kShiftScene, torch::kFloat64).unsqueeze(0);
  CHECK_THROWS_WITH(fit_shift_factor(G, torch::zeros({1, kShiftRows, kShiftScene}, torch::kFloat64), 0.0, {}, 10),
                    Contains("non-zero shift"));
}

TEST_CASE("pairs with no signal are named before the solve: flat grey scenes, lens-cap captures",
          "[optics][calibrate][errors]") {
  const SmallCamera camera(2);
  DatasetCalibrationOptions o;
  o.progress = false;
  for (const auto structure : {FactorStructure::Shift, FactorStructure::Free}) {
    o.structure = structure;
    auto grey = [&](int64_t i) {  // each photograph one grey level: no zero-mean part
      auto p = camera.capture(i, 0.01);
      p.scene = torch::full_like(p.scene, 0.1f * static_cast<float>(i % 7 + 1));
      return p;
    };
    CHECK_THROWS_WITH(calibrate_from_pairs(20, grey, kRows, kCols, kScene, o),
                      Contains("calibrate.dataset") && Contains("no contrast"));
    auto lens_cap = [&](int64_t i) {  // constant captures: nothing left after centring
      auto p = camera.capture(i, 0);
      p.meas = torch::zeros_like(p.meas);
      return p;
    };
    CHECK_THROWS_WITH(calibrate_from_pairs(20, lens_cap, kRows, kCols, kScene, o),
                      Contains("calibrate.dataset") && Contains("no signal"));
  }
}

TEST_CASE("each plane's shares of the display's primaries are identified with the factors (cross-talk)",
          "[optics][calibrate][colour-mix]") {
  const SmallCamera camera(5);
  // Each plane sees 80 % of its own primary and 10 % of each other's; rows b, gb, gr, r; columns R, G, B.
  const auto mix =
      torch::tensor({0.1, 0.1, 0.8, 0.1, 0.8, 0.1, 0.1, 0.8, 0.1, 0.8, 0.1, 0.1}, torch::kFloat64).view({4, 3});
  const auto load = [&](int64_t i) {
    auto pair = camera.capture(i, 0.0);  // its planes stand for R, G, B, and gb = gr
    const auto rgb = torch::stack({pair.scene[0], pair.scene[1], pair.scene[2]}).to(torch::kFloat64);
    const auto planes = torch::stack({rgb[2], rgb[1], rgb[1], rgb[0]});  // as photographs give them
    const auto seen = torch::einsum("ck,khw->chw", {mix, rgb});
    const auto s = seen.sum({1, 2}).view({4, 1, 1});
    auto gen = at::detail::createCPUGenerator(500 + static_cast<uint64_t>(i));
    auto Y = torch::matmul(torch::matmul(camera.P, seen), camera.Q.transpose(1, 2)) +
             s * torch::einsum("cr,cw->crw", {camera.a, camera.b});
    Y = Y + 0.01 * at::randn(Y.sizes(), gen).to(torch::kFloat64);
    return CapturePair{Y.to(torch::kFloat32), planes.to(torch::kFloat32), {}};
  };
  DatasetCalibrationOptions o;
  o.progress = false;
  o.structure = FactorStructure::Free;
  o.iterations = 40;
  o.tolerance = 1e-9;
  const auto fit = calibrate_from_pairs(300, load, kRows, kCols, kScene, o);
  REQUIRE(fit.colour_mix.defined());
  INFO(fit.colour_mix);
  CHECK((fit.colour_mix - mix).abs().max().item<double>() < 0.02);
  CHECK(calibration_error(fit.calib, {camera.P, camera.Q}).p < 0.03);
  // Without the mix the factors cannot explain what the other primaries add.
  o.identify_mix = false;
  const auto unmixed = calibrate_from_pairs(300, load, kRows, kCols, kScene, o);
  CHECK_FALSE(unmixed.colour_mix.defined());
  CHECK(unmixed.residual[0] > 3 * fit.residual[0]);
}
