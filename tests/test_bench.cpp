// A simulated bench's errors (optics/bench.hpp): each one does what it says, alone, and a camera
// file's bench: section is read and checked.
#include <ATen/CPUGeneratorImpl.h>

#include <fstream>

#include "catch_torch.hpp"
#include "core/error.hpp"
#include "helpers.hpp"
#include "io/camera_config.hpp"
#include "optics/bench.hpp"
#include "optics/camera.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

// The (row, col) of a tensor's largest value {H,W}.
std::pair<int64_t, int64_t> peak(const torch::Tensor& image) {
  const auto i = image.argmax().item<int64_t>();
  return {i / image.size(1), i % image.size(1)};
}

}  // namespace

TEST_CASE("bench errors: the display's shift and scale, cross-talk, stray light and hot pixels act as stated",
          "[optics][bench]") {
  // The photograph shown 2 pixels down and right: a point moves with it.
  auto scene = torch::zeros({3, 64, 64});
  scene.index_put_({torch::indexing::Slice(), 20, 30}, 1.0);
  BenchErrors shifted;
  shifted.display_shift = 2;
  CHECK(peak(bench_display(shifted, scene, c10::nullopt)[0]) == std::make_pair<int64_t, int64_t>(22, 32));
  CHECK(torch::equal(bench_display(BenchErrors{}, scene, c10::nullopt), scene));
  // Scaled by 1.25 about the centre (31.5): the point at 20 lands at 31.5 + 1.25 (20 - 31.5) = 17.1.
  BenchErrors scaled;
  scaled.display_scale = 1.25;
  CHECK(peak(bench_display(scaled, scene, c10::nullopt)[0]).first == 17);
  // Flicker scales the whole capture by one factor.
  BenchErrors flicker;
  flicker.flicker = 0.05;
  auto gen = at::make_generator<at::CPUGeneratorImpl>(3);
  const auto lit = bench_display(flicker, scene + 0.5, gen);
  const auto ratio = lit / (scene + 0.5);
  CHECK(ratio.max().item<double>() - ratio.min().item<double>() < 1e-5);
  CHECK(std::abs(ratio.mean().item<double>() - 1) > 1e-4);

  // Cross-talk 0.2: a red display is seen as 80 % red and 10 % in each other primary's plane.
  auto red = torch::zeros({3, 4, 4});
  red[0] = 1;
  BenchErrors crosstalk;
  crosstalk.crosstalk = 0.2;
  const auto mixed = bench_crosstalk(crosstalk, red);
  CHECK(mixed[0].mean().item<double>() == Approx(0.8));
  CHECK(mixed[1].mean().item<double>() == Approx(0.1));
  CHECK(mixed[2].mean().item<double>() == Approx(0.1));

  // Stray light rises from 0 at the top-left to stray_light at the bottom-right.
  const auto rig = load_rig(test::rig_path());
  const auto planes = torch::zeros({1, 4, rig.scene_size(), rig.scene_size()});
  const auto dark = expected_signal(rig, planes);
  BenchErrors stray;
  stray.stray_light = 0.01;
  const auto with_stray = bench_signal(stray, rig, planes, dark);
  CHECK(with_stray[0][0][0][0].item<double>() == Approx(0).margin(1e-9));
  CHECK(with_stray[0][2][-1][-1].item<double>() == Approx(0.01));

  // Hot pixels: that many places, the same ones every frame, stuck at 40-100 % of full scale.
  BenchErrors hot;
  hot.hot_pixels = 300;
  const auto raw = torch::zeros({64, 80}, torch::kInt32);
  const auto a = bench_hot_pixels(hot, raw, 10), b = bench_hot_pixels(hot, raw, 10);
  CHECK(torch::equal(a, b));
  CHECK((a > 0).sum().item<int64_t>() == 300);
  CHECK(a.max().item<int64_t>() <= 65535);
  CHECK(a.masked_select(a > 0).min().item<int64_t>() >= static_cast<int64_t>(0.39 * 65535));
}

TEST_CASE("bench errors: a rotated mask turns the response, and a second term adds a weak ghost of it",
          "[optics][bench]") {
  const auto rig = load_rig(test::rig_path());
  const auto n = rig.scene_size();
  torch::manual_seed(5);
  const auto planes = torch::rand({1, 4, n, n});  // a random scene: coded light with structure everywhere
  const auto signal = expected_signal(rig, planes);
  // A rotation of 0.01 rad about the plane's centre moves a column 200 pixels right of it down by 2.
  BenchErrors rotated;
  rotated.mask_rotation = 0.01;
  const auto turned = bench_signal(rotated, rig, planes, signal);
  const auto h = signal.size(2), w = signal.size(3);
  const auto column = w / 2 + 200;
  const auto profile = [&](const torch::Tensor& s) { return s[0][0].select(1, column); };
  // The shift that best aligns the column's profile before and after.
  int64_t best = 0;
  double best_error = 1e30;
  for (int64_t d = -5; d <= 5; ++d) {
    const auto err =
        (torch::roll(profile(signal), d) - profile(turned)).slice(0, 10, h - 10).pow(2).sum().item<double>();
    if (err < best_error) best_error = err, best = d;
  }
  CHECK(std::abs(best) == 2);
  // The second term: 5 % of the coded response (the open part's light carries no code), shifted, added.
  BenchErrors ghost;
  ghost.second_term = 0.05;
  auto coded_only = rig;
  coded_only.vig_rows = torch::zeros_like(rig.vig_rows);
  coded_only.vig_cols = torch::zeros_like(rig.vig_cols);
  const auto coded = expected_signal(coded_only, planes);
  const auto added = bench_signal(ghost, coded_only, planes, coded) - coded;
  CHECK(added.norm().item<double>() / coded.norm().item<double>() == Approx(0.05).epsilon(0.2));
  CHECK(torch::equal(bench_signal(BenchErrors{}, rig, planes, signal), signal));
}

TEST_CASE("bench errors: a calibration that errs changes each capture's coded light by its share, around the truth",
          "[optics][bench]") {
  const auto rig = load_rig(test::rig_path());
  const auto n = rig.scene_size();
  torch::manual_seed(6);
  const auto planes = torch::rand({1, 4, n, n});
  const auto signal = expected_signal(rig, planes);
  CHECK(torch::equal(bench_calibration(BenchErrors{}, rig, planes, signal, c10::nullopt), signal));
  auto coded_only = rig;  // the coded light alone: the open part's light is not the calibration's
  coded_only.vig_rows = torch::zeros_like(rig.vig_rows);
  coded_only.vig_cols = torch::zeros_like(rig.vig_cols);
  const auto coded = expected_signal(coded_only, planes);
  const auto change = [&](double error, uint64_t seed) {
    BenchErrors erring;
    erring.calibration_error = error;
    auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
    return bench_calibration(erring, rig, planes, signal, gen) - signal;
  };
  // Each channel's coded light changes by exactly that share of it.
  const auto share = change(0.03, 1).norm(2, {2, 3}) / coded.norm(2, {2, 3});
  CHECK(torch::allclose(share, torch::full_like(share, 0.03), 1e-3));
  // Redrawn for every capture, and zero-mean: 16 draws average to about a quarter of one draw's change.
  CHECK_FALSE(torch::allclose(change(0.03, 1), change(0.03, 2)));
  auto sum = torch::zeros_like(signal);
  for (uint64_t seed = 1; seed <= 16; ++seed) sum += change(0.03, seed);
  CHECK((sum / 16).norm().item<double>() / change(0.03, 1).norm().item<double>() == Approx(0.25).epsilon(0.25));
}

TEST_CASE("a camera file's bench section is read, and a value out of range or an unknown error is named",
          "[optics][bench][config]") {
  test::Scratch s("bench_camera");
  const auto write = [&](const std::string& bench) {
    std::ofstream(s.dir / "camera.yaml") << "name: bench\nrig: " << test::rig_path().string() << "\nbench:\n" << bench;
    return s.dir / "camera.yaml";
  };
  const auto camera = load_camera_config(
      write("  crosstalk: 0.2\n  mask_rotation: 0.004\n  hot_pixels: 300\n  calibration_error: 0.03\n"));
  CHECK(camera.bench.calibration_error == 0.03);
  CHECK(camera.bench.crosstalk == 0.2);
  CHECK(camera.bench.mask_rotation == 0.004);
  CHECK(camera.bench.hot_pixels == 300);
  CHECK(camera.bench.any());
  CHECK(load_camera_rig(camera).bench.hot_pixels == 300);
  CHECK_FALSE(load_camera_config(test::source_dir() / "configs" / "cameras" / "sim.yaml").bench.any());
  CHECK_THROWS_WITH(load_camera_config(write("  crosstalk: 0.9\n")),
                    Contains("camera.yaml") && Contains("bench.crosstalk") && Contains("0.5"));
  CHECK_THROWS_WITH(load_camera_config(write("  ghosts: 1\n")), Contains("unknown bench error 'bench.ghosts'"));
  CHECK_THROWS_WITH(load_camera_config(write("  calibration_error: -0.1\n")),
                    Contains("bench.calibration_error") && Contains("0 to 0.5"));
  // The bench is the simulated camera's truth, never a model's: model files keep the geometry only.
  CHECK_THAT(camera_geometry_yaml(camera), !Contains("bench:") && !Contains("crosstalk"));
}
