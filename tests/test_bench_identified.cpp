// What `calibrate --dataset` identifies of a real bench and the camera file keeps: hot pixels, found
// from a camera's own captures (optics/hot_pixels.hpp), listed in its camera file and repaired before
// anything else reads a capture (io/raw.hpp repair_hot_pixels); the colour mix (cross-talk between
// the display's primaries, optics/calibrate_dataset.hpp), written to the camera file and undone by
// classical reconstruction (io/image.hpp unmix_primaries).
#include <ATen/CPUGeneratorImpl.h>

#include <fstream>

#include "catch_torch.hpp"
#include "core/error.hpp"
#include "helpers.hpp"
#include "io/camera_config.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"
#include "optics/bench.hpp"
#include "optics/camera.hpp"
#include "optics/hot_pixels.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;
using HotList = std::vector<std::array<int64_t, 2>>;

TEST_CASE("a listed hot pixel is replaced by the mean of its same-colour neighbours that are not listed",
          "[io][raw][hot-pixels]") {
  torch::manual_seed(1);
  const auto planes = torch::rand({4, 8, 10});
  // Raw (5, 6) is plane gr (odd row, even column) at (2, 3); raw (5, 8) its right-hand neighbour there.
  auto broken = planes.clone();
  broken[2][2][3] = 1e3;
  broken[2][2][4] = -1e3;
  const auto repaired = repair_hot_pixels(broken, {{5, 6}, {5, 8}});
  const auto gr = planes[2];
  // (2, 3)'s neighbours less the listed (2, 4): 7 values.
  const double expected = (gr.slice(0, 1, 4).slice(1, 2, 5).sum() - gr[2][3] - gr[2][4]).item<double>() / 7;
  CHECK(repaired[2][2][3].item<double>() == Approx(expected));
  // Everything unlisted is untouched, in every plane.
  auto unlisted = torch::ones({4, 8, 10}, torch::kBool);
  unlisted[2][2][3] = false;
  unlisted[2][2][4] = false;
  CHECK(torch::equal(repaired.masked_select(unlisted), planes.masked_select(unlisted)));
  CHECK(torch::equal(repair_hot_pixels(planes, {}), planes));
  // raw_window repairs before it rotates and crops.
  RawGeometry g;
  g.raw_height = 16;
  g.raw_width = 20;
  g.crop = {0, 0, 8, 10};
  g.hot_pixels = {{5, 6}, {5, 8}};
  CHECK(torch::allclose(raw_window(bayer_merge(broken), g), repaired));
}

TEST_CASE("the median of 8 neighbours is sort's middle two averaged, ties and negatives included",
          "[optics][hot-pixels]") {
  torch::manual_seed(4);
  // Few distinct values make ties common; every order of them is hit many times over.
  const auto x = torch::randint(-3, 4, {3, 8, 20000}).to(torch::kFloat32);
  const auto sorted = std::get<0>(x.sort(1));
  CHECK(torch::equal(median_of_eight(x), (sorted.select(1, 3) + sorted.select(1, 4)) / 2));
  const auto smooth = torch::randn({2, 8, 5000});
  const auto s2 = std::get<0>(smooth.sort(1));
  CHECK(torch::equal(median_of_eight(smooth), (s2.select(1, 3) + s2.select(1, 4)) / 2));
  CHECK_THROWS_WITH(median_of_eight(torch::zeros({2, 7, 3})), Contains("{P,8,N}"));
}

TEST_CASE("hot pixels are found from captures of varied scenes, and none on a sensor without them",
          "[optics][hot-pixels]") {
  // The simulated bench's 300 stuck pixels (optics/bench.hpp) in 16 noisy captures of random scenes.
  const auto rig = load_rig(test::rig_path());
  auto with_hot = rig;
  with_hot.bench.hot_pixels = 300;
  HotPixelFinder clean({12, rig.adc_bits}), hot({12, rig.adc_bits});
  auto gen = at::make_generator<at::CPUGeneratorImpl>(11);
  for (int k = 0; k < 16; ++k) {
    // One capture in four at the display's full white, where the sensor clips (16 such captures leave
    // too few unclipped neighbours to judge most pixels): pixels beside clipped ones sit it out.
    const double brightness = k % 4 == 0 ? 1.0 : 0.3;
    const auto scene = at::rand({3, rig.scene_size(), rig.scene_size()}, gen) * brightness;
    auto g1 = at::make_generator<at::CPUGeneratorImpl>(100 + k), g2 = at::make_generator<at::CPUGeneratorImpl>(100 + k);
    clean.add(simulate_raw_linear(rig, scene, true, g1).to(torch::kFloat32) / 65535.0);
    hot.add(simulate_raw_linear(with_hot, scene, true, g2).to(torch::kFloat32) / 65535.0);
  }
  CHECK(clean.find().empty());
  // The truth: where the bench raises a dark frame.
  const int64_t H = rig.phil.size(1) * 2, W = rig.phir.size(1) * 2;
  const auto stuck = bench_hot_pixels(with_hot.bench, torch::zeros({H, W}, torch::kInt32), rig.adc_bits) > 0;
  const auto found = hot.find();
  REQUIRE(found.size() >= 290);  // a stuck level below a bright pixel's own light never shows
  for (const auto& [row, col] : found) CHECK(stuck[row][col].item<bool>());
}

TEST_CASE("a camera file's hot_pixels are read, written back and checked against the frame",
          "[io][config][hot-pixels]") {
  test::Scratch s("hot_camera");
  const auto write = [&](const std::string& list) {
    std::ofstream(s.dir / "camera.yaml") << "name: hot\nraw_height: 1024\nraw_width: 1280\nhot_pixels: " << list
                                         << "\n";
    return s.dir / "camera.yaml";
  };
  const auto camera = load_camera_config(write("[[5, 6], [1023, 1279]]"));
  CHECK((camera.raw.hot_pixels == HotList{{5, 6}, {1023, 1279}}));
  // Model files and written camera files carry the list.
  const auto again = camera_from_yaml_text(camera_geometry_yaml(camera), "model");
  CHECK((again.raw.hot_pixels == camera.raw.hot_pixels));
  CHECK_THAT(camera_geometry_yaml(load_camera_config(write("[]"))), !Contains("hot_pixels"));
  CHECK_THROWS_WITH(load_camera_config(write("[[1024, 0]]")),
                    Contains("camera.yaml") && Contains("[1024, 0] lies outside the 1024x1280 raw frame"));
  CHECK_THROWS_WITH(load_camera_config(write("[[-1, 3]]")), Contains("hot_pixels: [-1, 3] lies outside"));
  CHECK_THROWS_WITH(load_camera_config(write("[5, 6]")), Contains("each entry is [row, col]"));
  CHECK_THROWS_WITH(load_camera_config(write("7")), Contains("expected a list"));
}

TEST_CASE("a camera file's colour_mix is read, written back and checked, and unmixing recovers the primaries",
          "[io][config][colour-mix]") {
  test::Scratch s("mix_camera");
  const auto write = [&](const std::string& mix) {
    std::ofstream(s.dir / "camera.yaml") << "name: mixed\ncolour_mix: " << mix << "\n";
    return s.dir / "camera.yaml";
  };
  const auto camera = load_camera_config(write("[[0.1, 0.1, 0.8], [0.1, 0.8, 0.1], [0.1, 0.8, 0.1], [0.8, 0.1, 0.1]]"));
  REQUIRE(camera.colour_mix.size() == 4);
  CHECK(camera.colour_mix[3][0] == 0.8);
  CHECK((camera_from_yaml_text(camera_geometry_yaml(camera), "model").colour_mix == camera.colour_mix));
  CHECK_THROWS_WITH(load_camera_config(write("[[1, 0, 0], [0, 1, 0], [0, 1, 0]]")), Contains("4 rows"));
  CHECK_THROWS_WITH(load_camera_config(write("[[1, 0], [0, 1], [0, 1], [1, 0]]")), Contains("3 shares"));
  // Two primaries that look alike to every plane cannot be told apart.
  CHECK_THROWS_WITH(load_camera_config(write("[[0.5, 0.5, 0], [0.5, 0.5, 0], [0.5, 0.5, 0], [0, 0, 1]]")),
                    Contains("camera.yaml") && Contains("cannot be undone"));
  // Planes that see the mix give the primaries back.
  torch::manual_seed(2);
  const auto rgb = torch::rand({2, 3, 5, 5});
  const auto mix = colour_mix_matrix(camera.colour_mix).to(torch::kFloat32);
  const auto planes = torch::einsum("ck,bkhw->bchw", {mix, rgb});
  CHECK(torch::allclose(unmix_primaries(planes, mix), rgb, 1e-4, 1e-5));
  CHECK(torch::allclose(bayer_planes_to_rgb(rgb_to_bayer_planes(rgb)), rgb));
}
