#pragma once
#include <set>
#include <string>

#include <catch2/catch.hpp>

// A FlatNet generator small enough for unit tests (20x24 measurement planes -> 16x16 scene), and
// the check that gradients reach every parameter.
#include "io/camera_config.hpp"
#include "nn/generator.hpp"
#include "io/config.hpp"
#include "nn/model_file.hpp"

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

// The biases of convolutions that feed a batch norm directly: in train mode the batch mean removes
// them, so their gradient is zero up to rounding (which is sometimes exactly 0).
inline std::set<std::string> biases_before_batchnorm(torch::nn::Module& m) {
  std::set<std::string> out;
  for (const auto& item : m.named_modules()) {
    const auto children = item.value()->named_children();
    for (size_t i = 0; i + 1 < children.size(); ++i)
      if (children[i].value()->as<torch::nn::Conv2d>() && children[i + 1].value()->as<torch::nn::BatchNorm2d>())
        out.insert((item.key().empty() ? "" : item.key() + ".") + children[i].key() + ".bias");
  }
  return out;
}

// Every parameter is in the graph; every one that can change the loss in train mode does.
inline void check_all_gradients(torch::nn::Module& m, const torch::Tensor& loss) {
  loss.backward();
  const auto absorbed = biases_before_batchnorm(m);
  for (const auto& p : m.named_parameters()) {
    INFO(p.key());
    REQUIRE(p.value().grad().defined());
    if (!m.is_training() || !absorbed.count(p.key())) CHECK(p.value().grad().abs().sum().item<double>() > 0);
  }
}

}  // namespace test
