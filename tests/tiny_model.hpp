#pragma once
// A FlatNet generator small enough for unit tests: 20x24 measurement planes -> 16x16 scene.
#include "core/camera_config.hpp"
#include "nn/generator.hpp"
#include "train/config.hpp"
#include "train/model_file.hpp"

namespace test {

inline flatnet::CameraConfig tiny_camera(flatnet::Centring centring = flatnet::Centring::plane) {
  flatnet::CameraConfig c;
  c.raw.crop = {0, 0, 20, 24};
  c.scene_size = 16;
  c.raw.centring = centring;
  return c;
}

// A trained-looking generator for `config` on `camera`: random weights in [-0.3, 0.3], batch-norm
// statistics from one batch, eval mode.
inline flatnet::Generator random_generator(const flatnet::Config& config, const flatnet::CameraConfig& camera) {
  flatnet::Generator g(flatnet::generator_options(config, camera, false));
  torch::NoGradGuard ng;
  for (auto& p : g->parameters()) p.uniform_(-0.3, 0.3);
  g->train();
  g->forward(torch::randn({2, 4, 20, 24}) + 0.5);
  g->eval();
  return g;
}

}  // namespace test
