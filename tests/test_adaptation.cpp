// Test-time adaptation (recon/adaptation.hpp, eq. 1): a few Adam steps on the captures' own
// disagreement with the model's pictures bring the pictures toward what the captures measure; the
// pull to the shipped weights holds them nearer; the first stage never moves; the captures used are
// spread over those given; bad settings are named.
#include "catch_torch.hpp"

#include <map>

#include "consistency_bench.hpp"
#include "io/camera_config.hpp"
#include "io/image.hpp"
#include "recon/adaptation.hpp"
#include "recon/data_consistency.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

constexpr int64_t kRows = test::kBenchRows, kCols = test::kBenchCols, kScene = test::kBenchScene;

struct Bench : test::SmallCamera {
  std::vector<torch::Tensor> captures;  // three scenes, each {4,h,w}
  Bench() : SmallCamera(11) {
    auto gen = at::detail::createCPUGenerator(12);
    for (int k = 0; k < 3; ++k) {
      const auto rgb = 0.1 + 0.8 * at::rand({1, 3, kScene, kScene}, gen).to(torch::kFloat64);
      const auto X = rgb_to_bayer_planes(rgb);
      captures.push_back(
          torch::matmul(torch::matmul(calib.P, X), calib.Q.transpose(1, 2)).squeeze(0).to(torch::kFloat32));
    }
  }
};

AdaptationOptions quick(double anchor) {
  AdaptationOptions o;
  o.steps = 100, o.batch = 3, o.lr = 3e-3, o.anchor = anchor, o.brightness = 0;
  return o;
}

}  // namespace

TEST_CASE("test-time adaptation lowers the captures' disagreement, and its anchor holds the weights nearer",
          "[recon][adaptation]") {
  Bench b;
  const DataConsistency measure(b.calib, b.camera, {});
  auto free = test::small_generator();
  free->eval();  // as adaptation runs it: a forward pass in training mode would move the batch norms
  const auto before = free->forward(torch::stack(b.captures)).detach();
  std::map<std::string, torch::Tensor> first_stage;  // the camera's own inversion: never adapted
  for (const auto& item : free->named_parameters())
    if (item.key().rfind("inversion.", 0) == 0) first_stage[item.key()] = item.value().detach().clone();
  REQUIRE_FALSE(first_stage.empty());
  const auto loose = adapt_to_captures(free, b.captures, measure, quick(0));
  for (const auto& item : free->named_parameters())
    if (first_stage.count(item.key())) CHECK(torch::equal(item.value(), first_stage[item.key()]));
  CHECK(loose.captures == 3);
  CHECK(loose.steps == 100);
  CHECK(loose.disagreement_after < 0.9 * loose.disagreement_before);
  CHECK(loose.distance > 0);
  CHECK((free->forward(torch::stack(b.captures)) - before).abs().max().item<double>() > 1e-3);
  CHECK_THAT(loose.summary(), Contains("adapted to 3 captures in 100 steps"));

  // The brightness term keeps each picture's mean nearer the shipped model's.
  const auto drift_of = [&](Generator& g) {
    g->eval();
    return (g->forward(torch::stack(b.captures)).mean() / before.mean() - 1).abs().item<double>();
  };
  auto steady = test::small_generator();
  auto o = quick(0);
  o.brightness = 1e3;
  adapt_to_captures(steady, b.captures, measure, o);
  CHECK(drift_of(steady) < 0.5 * drift_of(free));

  auto held = test::small_generator();
  const auto anchored = adapt_to_captures(held, b.captures, measure, quick(1e6));
  CHECK(anchored.distance < 0.5 * loose.distance);
  CHECK(std::abs(anchored.disagreement_before - loose.disagreement_before) < 1e-9);  // the same start
}

TEST_CASE("test-time adaptation spreads the captures it uses and names bad settings", "[recon][adaptation]") {
  std::vector<std::filesystem::path> all;
  for (int k = 0; k < 10; ++k) all.push_back("c" + std::to_string(k) + ".png");
  AdaptationOptions o;
  o.captures = 4;
  const auto chosen = adaptation_captures(all, o);
  REQUIRE(chosen.size() == 4);
  CHECK(chosen[0] == "c0.png");
  CHECK(chosen[1] == "c2.png");
  CHECK(chosen[2] == "c5.png");
  CHECK(chosen[3] == "c7.png");
  o.captures = 32;
  CHECK(adaptation_captures(all, o).size() == 10);

  const auto bad = [](auto change) {
    AdaptationOptions o;
    change(o);
    return o;
  };
  CHECK_THROWS_WITH(check_adaptation_options(bad([](auto& o) { o.steps = -1; })), Contains("adapt_steps"));
  CHECK_THROWS_WITH(check_adaptation_options(bad([](auto& o) { o.steps = 1000000; })), Contains("adapt_steps"));
  CHECK_THROWS_WITH(check_adaptation_options(bad([](auto& o) { o.lr = 0; })), Contains("adapt_lr"));
  CHECK_THROWS_WITH(check_adaptation_options(bad([](auto& o) { o.lr = NAN; })), Contains("adapt_lr"));
  CHECK_THROWS_WITH(check_adaptation_options(bad([](auto& o) { o.anchor = -1; })), Contains("adapt_anchor"));
  CHECK_THROWS_WITH(check_adaptation_options(bad([](auto& o) { o.batch = 0; })), Contains("adapt_batch"));
  CHECK_THROWS_WITH(check_adaptation_options(bad([](auto& o) { o.brightness = -1; })), Contains("adapt_brightness"));
  CHECK_THROWS_WITH(check_adaptation_options(bad([](auto& o) { o.captures = 0; })), Contains("adapt_captures"));
}
