// Test-time self-ensemble (InferenceLevers::self_ensemble, `infer --self-ensemble`).
#include "catch_torch.hpp"

#include "helpers.hpp"
#include "nn/generator.hpp"
#include "tiny_model.hpp"

using namespace flatnet;

TEST_CASE("flip_ensemble undoes each flip and averages the four views", "[nn][ensemble]") {
  const auto x = torch::rand({2, 3, 5, 7});
  // A position-dependent gain is not flip-equivariant: the ensemble's gain is its flip average.
  const auto gain = torch::rand({1, 1, 5, 7}) + 0.5;
  int calls = 0;
  const auto f = [&](const torch::Tensor& batch) {
    ++calls;
    CHECK(batch.size(0) == 8);  // the four views in one batch
    return batch * gain;
  };
  const auto expected = x * (gain + torch::flip(gain, {3}) + torch::flip(gain, {2}) + torch::flip(gain, {2, 3})) / 4.0;
  CHECK(torch::allclose(flip_ensemble(f, x), expected, 1e-6, 1e-6));
  CHECK(calls == 1);
  // A flip-equivariant function (elementwise) comes out as itself.
  const auto square = [](const torch::Tensor& batch) { return batch * batch; };
  CHECK(torch::allclose(flip_ensemble(square, x), x * x, 1e-6, 1e-6));
}

TEST_CASE("a generator with self-ensemble averages its enhancer in inference only", "[nn][ensemble]") {
  const auto config = Config::load({}, {"model.unet.width=2"});
  const auto camera = test::tiny_camera();
  torch::manual_seed(3);
  auto plain = test::random_generator(config, camera);
  torch::manual_seed(3);
  auto ensembled = test::random_generator(config, camera);
  auto levers = parse_inference_levers("none");
  plain->prepare_inference(levers);
  levers.self_ensemble = true;
  ensembled->prepare_inference(levers);
  torch::NoGradGuard no_grad;
  const auto Y = torch::randn({2, 4, 20, 24}) + 0.5;  // {B,4,rows,cols}
  const auto a = plain->forward(Y), b = ensembled->forward(Y);
  CHECK(b.sizes() == a.sizes());
  CHECK(b.min().item<float>() >= 0);
  CHECK(b.max().item<float>() <= 1);
  CHECK_FALSE(torch::allclose(a, b));  // a random U-Net is not flip-equivariant
  // Training never ensembles: the same weights give the plain output in train mode.
  ensembled->train();
  plain->train();
  CHECK(torch::allclose(plain->forward(Y), ensembled->forward(Y)));
}
