#pragma once
// A small camera for the data-consistency and adaptation tests: random centred factors (as
// calibrations are after centring), {4,40,16} and {4,48,16}, plane centring, tikhonov_lambda 1e-2.
#include <torch/torch.h>

#include "io/camera_config.hpp"
#include "nn/generator.hpp"
#include "optics/camera.hpp"

namespace flatnet::test {

constexpr int64_t kBenchRows = 40, kBenchCols = 48, kBenchScene = 16;

struct SmallCamera {
  Calibration calib;
  CameraConfig camera;
  explicit SmallCamera(uint64_t seed) {
    auto gen = at::detail::createCPUGenerator(seed);
    auto centred = [](torch::Tensor F) { return F - F.mean(1, true); };
    calib = {centred(at::rand({4, kBenchRows, kBenchScene}, gen).to(torch::kFloat64)),
             centred(at::rand({4, kBenchCols, kBenchScene}, gen).to(torch::kFloat64))};
    camera.raw.crop = {0, 0, kBenchRows, kBenchCols};
    camera.scene_size = kBenchScene;
    camera.raw.centring = Centring::plane;
    camera.tikhonov_lambda = 1e-2;
  }
};

// A small random FlatNet generator for this camera: random first stage, a U-Net of width 2.
inline Generator small_generator() {
  torch::manual_seed(3);
  GeneratorOptions o;
  o.rows = kBenchRows, o.cols = kBenchCols, o.scene = kBenchScene;
  o.inversion.phil = torch::randn({kBenchRows, kBenchScene, 1}) * 0.2;
  o.inversion.phir = torch::randn({kBenchCols, kBenchScene, 1}) * 0.2;
  o.unet.width = 2;
  return Generator(o);
}

}  // namespace flatnet::test
