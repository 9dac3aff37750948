// Run-time precision: CPU feature detection, the auto choice, and bf16 autocast training that
// tracks fp32 (emulated bf16 is slow but correct, so this runs on every machine).
#include <catch2/catch.hpp>

#include <ATen/autocast_mode.h>

#include "core/error.hpp"
#include "core/precision.hpp"
#include "nn/generator.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

TEST_CASE("cpuinfo flags decide whether bf16 is native", "[precision]") {
  const std::string amx = "processor\t: 0\nmodel name\t: Intel(R) Xeon(R) Platinum 8480+\n"
                          "flags\t\t: fpu avx2 avx512f avx512_bf16 amx_bf16 amx_tile\n\nprocessor\t: 1\nflags\t\t: fpu\n";
  const auto a = parse_cpuinfo(amx);
  CHECK(a.model == "Intel(R) Xeon(R) Platinum 8480+");
  CHECK((a.avx512f && a.avx512_bf16 && a.amx_bf16));
  CHECK(a.bf16_engine() == "AMX");
  CHECK(resolve_precision("auto", a, "--precision") == Precision::bf16);
  CHECK(describe_precision(Precision::bf16, a) == "bf16 (AMX)");
  const auto b = parse_cpuinfo("model name : Xeon\nflags : fpu avx2 avx512f avx512bw\n");
  CHECK_FALSE(b.native_bf16());
  CHECK(resolve_precision("auto", b, "--precision") == Precision::fp32);
  CHECK(resolve_precision("bf16", b, "--precision") == Precision::bf16);  // asked for: allowed, but said to be slow
  CHECK_THAT(describe_precision(Precision::bf16, b), Contains("emulated"));
  CHECK(parse_cpuinfo("model name : X\nflags : avx512_bf16\n").bf16_engine() == "AVX512-BF16");
  CHECK_THROWS_WITH(resolve_precision("fp16", a, "train.precision"), Contains("train.precision") && Contains("auto, fp32 or bf16"));
  CHECK_FALSE(cpu_features().summary().empty());
}

TEST_CASE("autocast guards nest and restore the thread's state", "[precision]") {
  CHECK_FALSE(at::autocast::is_cpu_enabled());
  {
    AutocastGuard outer(true);
    CHECK(at::autocast::is_cpu_enabled());
    CHECK(at::autocast::get_autocast_cpu_dtype() == at::kBFloat16);
    const auto a = torch::randn({4, 4}), b = torch::randn({4, 4});
    CHECK(torch::mm(a, b).scalar_type() == torch::kBFloat16);
    {
      AutocastOffGuard off;
      CHECK(torch::mm(a, b).scalar_type() == torch::kFloat32);
    }
    CHECK(at::autocast::is_cpu_enabled());
    { AutocastGuard inner(false); CHECK(at::autocast::is_cpu_enabled()); }
  }
  CHECK_FALSE(at::autocast::is_cpu_enabled());
}

TEST_CASE("a short bf16 autocast training run tracks the fp32 loss curve", "[precision][bf16]") {
  // The same tiny generator, data and optimiser, once in fp32 and once with the enhancer under
  // bf16 autocast (master weights and Adam in fp32): the curves must agree within bf16's noise.
  auto run = [](bool bf16) {
    torch::manual_seed(21);
    GeneratorOptions o;
    o.rows = 20, o.cols = 24, o.scene = 16;
    o.inversion.phil = torch::randn({20, 16, 1}) * 0.2;
    o.inversion.phir = torch::randn({24, 16, 1}) * 0.2;
    o.unet.width = 4;
    Generator g(o);
    g->prepare_training({false, true, false, true});
    g->set_autocast_bf16(bf16);
    torch::optim::Adam opt(g->parameters(), 3e-3);
    auto gen = at::detail::createCPUGenerator(5);
    const auto Y = at::randn({4, 4, 20, 24}, gen) * 0.1;
    const auto target = at::rand({4, 3, 16, 16}, gen);
    std::vector<double> curve;
    for (int step = 0; step < 30; ++step) {
      opt.zero_grad();
      const auto loss = torch::mse_loss(g->forward(Y), target);
      loss.backward();
      opt.step();
      curve.push_back(loss.item<double>());
    }
    return curve;
  };
  const auto fp32 = run(false), bf16 = run(true);
  CHECK(fp32.back() < 0.7 * fp32.front());  // it learns
  CHECK(bf16.back() < 0.7 * bf16.front());
  for (size_t i = 0; i < fp32.size(); i += 5) {
    INFO("step " << i << ": fp32 " << fp32[i] << ", bf16 " << bf16[i]);
    CHECK(std::abs(bf16[i] - fp32[i]) <= 0.05 * fp32[i]);
  }
}
