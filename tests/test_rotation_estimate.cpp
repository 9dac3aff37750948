// The mask's rotation estimated from display-capture pairs (optics/rotation_estimate): on a small
// camera whose separable response is rotated on the sensor, the residual's projection on the
// rotation's signature changes sign at the true angle, and the secant search finds it.
#include <cmath>

#include "catch_torch.hpp"

#include "core/error.hpp"
#include "io/raw.hpp"
#include "optics/rotation_estimate.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

constexpr int64_t kPlaneRows = 72, kPlaneCols = 84, kScene = 16;
constexpr std::array<int64_t, 2> kOrigin = {8, 8};
constexpr int64_t kRows = 56, kCols = 68;  // the window

// A FlatCam-like camera on whole planes {4,72,84}: each factor's column j is one smooth random profile
// moved by 2 j pixels (the mask's shadow), and the mask rotated by `angle` on the sensor: the sensor
// reads the separable planes at rotated coordinates, so rotating a capture by `angle` (io/raw.hpp
// rotate_planes) gives them back.
struct RotatedCamera {
  torch::Tensor P, Q;
  double angle;
  RotatedCamera(double angle, uint64_t seed) : angle(angle) {
    auto gen = at::detail::createCPUGenerator(seed);
    P = shadow(kPlaneRows, gen);
    Q = shadow(kPlaneCols, gen);
  }
  static torch::Tensor shadow(int64_t length, at::Generator& gen) {
    const int64_t span = length + 2 * kScene + 2;
    auto code = at::rand({4, span}, gen).to(torch::kFloat64);
    code = (code.narrow(1, 0, span - 2) + code.narrow(1, 1, span - 2) + code.narrow(1, 2, span - 2)) / 3;
    std::vector<torch::Tensor> columns;
    for (int64_t j = 0; j < kScene; ++j) columns.push_back(code.narrow(1, 2 * j, length));
    return torch::stack(columns, 2);  // {4,length,kScene}
  }
  torch::Tensor scene(int64_t i) const {
    auto gen = at::detail::createCPUGenerator(500 + static_cast<uint64_t>(i));
    return at::rand({4, kScene, kScene}, gen).to(torch::kFloat64);
  }
  // The sensor's planes of scene i, rotated by -angle (what rotating back by +angle undoes).
  torch::Tensor sensor(int64_t i) const {
    return rotate_planes(torch::matmul(torch::matmul(P, scene(i)), Q.transpose(1, 2)), -angle);
  }
};

struct Probe {
  const RotatedCamera& camera;
  int64_t count;
  double operator()(double t) const {
    RawGeometry g;
    g.rotation = t;
    g.crop = {kOrigin[0], kOrigin[1], kRows, kCols};
    const auto window_pair = [&](int64_t i) {
      return WindowPair{rotated_window(camera.sensor(i), g), camera.scene(i), torch::Tensor()};  // no mask: every pixel
    };
    DatasetCalibrationOptions o;
    o.progress = false;
    o.structure = FactorStructure::Free;
    o.identify_mix = false;
    o.iterations = 25;
    o.tolerance = 1e-9;
    const auto fit = calibrate_from_pairs(
        count,
        [&](int64_t i) {
          const auto w = window_pair(i);
          return CapturePair{double_centre(w.window, Centring::plane), w.scene, {}};
        },
        kRows, kCols, kScene, o);
    return rotation_residual_projection(count, window_pair, fit, kOrigin);
  }
};

}  // namespace

TEST_CASE("the residual's rotation projection changes sign at the mask's true angle", "[optics][rotation]") {
  const RotatedCamera camera(0.02, 11);
  const Probe project{camera, 100};
  const double below = project(0.0), at = project(0.02), above = project(0.04);
  INFO("d(0) " << below << ", d(0.02) " << at << ", d(0.04) " << above);
  CHECK(below < 0);
  CHECK(above > 0);
  CHECK(std::abs(at) < 0.2 * std::min(std::abs(below), std::abs(above)));
}

TEST_CASE("the rotation search finds the mask's angle from a start of zero", "[optics][rotation]") {
  const RotatedCamera camera(-0.015, 5);
  const Probe project{camera, 100};
  RotationSearchOptions o;
  o.limit = 0.1;
  o.first_step = 0.01;
  o.tolerance = 2e-4;
  const auto search = search_rotation(project, o);
  INFO("angle " << search.angle << " after " << search.probes.size() << " fits");
  CHECK(search.angle == Approx(-0.015).margin(0.002));
  CHECK(search.probes.size() <= 5u);
}

TEST_CASE("the rotation search follows a secant and stops where the slope is wrong", "[optics][rotation]") {
  RotationSearchOptions o;
  // A linear d with a small slope (a noisy camera's k): the secant lands on the root.
  const auto linear = search_rotation([](double t) { return 0.02 * (t - 0.0037); }, o);
  CHECK(linear.converged);
  CHECK(linear.slope_found);
  CHECK(linear.angle == Approx(0.0037).margin(1e-6));
  CHECK(linear.probes.size() <= 4u);
  // A d that falls with the angle (no rotation signal, noise): the probe with the smallest |d|, here
  // the start, never an extrapolation.
  const auto flat = search_rotation([](double t) { return t < 0 ? 3e-6 : 1e-6; }, o);
  CHECK_FALSE(flat.converged);
  CHECK_FALSE(flat.slope_found);
  CHECK(flat.angle == 0.0);
  CHECK(flat.probes.size() == 2u);
  // Roots beyond the limit are clamped to it, around the start the camera file gives.
  o.start = 0.1;
  const auto far = search_rotation([](double t) { return 0.01 * (t - 0.5); }, o);
  CHECK(far.probes.front().angle == 0.1);
  CHECK(far.angle <= 0.1 + o.limit + 1e-12);
  CHECK(far.angle > 0.1);
  o.fits = 1;
  CHECK_THROWS_WITH(search_rotation([](double t) { return t; }, o), Contains("fits >= 2"));
}
