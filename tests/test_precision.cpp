// Run-time precision: CPU feature detection, the auto choice, and bf16 autocast training that
// tracks fp32 (emulated bf16 is slow but correct, so this runs on every machine).
#include "catch_torch.hpp"

#include <ATen/autocast_mode.h>

#include "core/blas.hpp"
#include "core/error.hpp"
#include "core/precision.hpp"
#include "io/raw.hpp"
#include "nn/model_file.hpp"
#include "nn/generator.hpp"
#include "nn/onednn_conv.hpp"
#include "helpers.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

TEST_CASE("cpuinfo flags decide whether bf16 is native", "[precision]") {
  const std::string amx =
      "processor\t: 0\nmodel name\t: Intel(R) Xeon(R) Platinum 8480+\n"
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
  CHECK_THROWS_WITH(resolve_precision("fp16", a, "train.precision"),
                    Contains("train.precision") && Contains("auto, fp32 or bf16"));
  CHECK_FALSE(cpu_features().summary().empty());
}

TEST_CASE("oneDNN's effective ISA decides what the CPU can do, so a cap and a missing kernel are alike",
          "[precision]") {
  // dnnl_cpu_isa_t values (oneDNN 2.6): avx2 0x7, avx512_core 0x27, avx512_core_bf16 0xe7, amx 0x3e7.
  const auto zen4 =
      parse_cpuinfo("model name : AMD EPYC\nflags : avx2 avx512f avx512cd avx512bw avx512dq avx512vl avx512_bf16\n");
  const auto native = with_onednn_isa(zen4, 0xe7);
  CHECK(native.native_bf16());
  CHECK(native.onednn_bf16);
  CHECK_FALSE(native.onednn_capped);
  CHECK(native.onednn_isa == "avx512_core_bf16");
  // ONEDNN_MAX_CPU_ISA=AVX2 on the same CPU: no AVX-512, no bf16 kernels, auto is fp32.
  const auto capped = with_onednn_isa(zen4, 0x7);
  CHECK_FALSE(capped.native_bf16());
  CHECK_FALSE(capped.avx512_core);
  CHECK_FALSE(capped.onednn_bf16);
  CHECK(capped.onednn_capped);
  CHECK(resolve_precision("auto", capped, "--precision") == Precision::fp32);
  CHECK_THAT(describe_precision(Precision::bf16, capped), Contains("LibTorch's own kernels") && Contains("avx2"));
  CHECK_THAT(capped.summary(), Contains("oneDNN capped at avx2"));
  // A real AVX2 CPU (Zen 3) is not "capped": it never had more.
  const auto zen3 = with_onednn_isa(parse_cpuinfo("model name : AMD EPYC 7B13\nflags : avx2 fma\n"), 0x7);
  CHECK_FALSE(zen3.onednn_capped);
  CHECK_FALSE(zen3.onednn_bf16);
  // AVX-512 without bf16 (Skylake): oneDNN emulates bf16.
  const auto skx =
      with_onednn_isa(parse_cpuinfo("model name : X\nflags : avx512f avx512cd avx512bw avx512dq avx512vl\n"), 0x67);
  CHECK(skx.onednn_bf16);
  CHECK_THAT(describe_precision(Precision::bf16, skx), Contains("emulated by oneDNN"));
  // OpenBLAS follows the cap: its AVX-512 kernels give way to Haswell's.
  CHECK(better_openblas_core("SkylakeX", capped, nullptr) == "Haswell");
  CHECK(better_openblas_core("Cooperlake", capped, nullptr) == "Haswell");
  CHECK(better_openblas_core("Haswell", capped, nullptr).empty());
  CHECK(better_openblas_core("SkylakeX", capped, "SkylakeX").empty());  // the user's choice stands
  CHECK(better_openblas_core("Zen", zen3, nullptr).empty());
}

TEST_CASE("bf16 convolutions run on every CPU kind: LibTorch's own kernels where oneDNN has none",
          "[precision][bf16]") {
  // Under ONEDNN_MAX_CPU_ISA=AVX2 (or below AVX-512) LibTorch would hand bf16 convolutions to
  // oneDNN and fail; inside a Bf16KernelScope they run on LibTorch's kernels.
  torch::manual_seed(4);
  const auto x = torch::randn({1, 8, 12, 12}), w = torch::randn({8, 8, 3, 3}) * 0.2;
  const auto fp32 = torch::conv2d(x, w, {}, 1, 1);
  const bool mkldnn_before = at::globalContext().userEnabledMkldnn();
  {
    const Bf16KernelScope scope;  // inference: for the scope's life only
    if (!cpu_features().onednn_bf16) CHECK_FALSE(at::globalContext().userEnabledMkldnn());
  }
  CHECK(at::globalContext().userEnabledMkldnn() == mkldnn_before);  // restored
  torch::Tensor bf16;
  {
    AutocastGuard autocast(true);  // training: for the rest of the process where oneDNN lacks bf16
    bf16 = torch::conv2d(x, w, {}, 1, 1);
  }
  if (!cpu_features().onednn_bf16) CHECK_FALSE(at::globalContext().userEnabledMkldnn());
  CHECK(bf16.scalar_type() == torch::kBFloat16);
  CHECK((bf16.to(torch::kFloat32) - fp32).abs().max().item<double>() <= 0.02 * fp32.abs().max().item<double>());
}

TEST_CASE("OpenBLAS gets its SkylakeX kernels on AVX-512 CPUs it predates, unless the user chose",
          "[precision][blas]") {
  const auto avx512 = parse_cpuinfo("model name : X\nflags : fpu avx2 avx512f avx512cd avx512bw avx512dq avx512vl\n");
  const auto avx2 = parse_cpuinfo("model name : X\nflags : fpu avx2 fma\n");
  const auto partial = parse_cpuinfo("model name : X\nflags : avx512f avx512cd\n");  // Knights Landing-like
  CHECK(avx512.avx512_core);
  CHECK_FALSE(partial.avx512_core);
  CHECK(better_openblas_core("Prescott", avx512, nullptr) == "SkylakeX");    // Emerald Rapids on 0.3.21
  CHECK(better_openblas_core("Cooperlake", avx512, nullptr) == "SkylakeX");  // Zen 5 on 0.3.21
  CHECK(better_openblas_core("Haswell", avx512, "") == "SkylakeX");
  CHECK(better_openblas_core("SkylakeX", avx512, nullptr).empty());
  CHECK(better_openblas_core("SapphireRapids", avx512, nullptr).empty());  // a newer OpenBLAS's own
  CHECK(better_openblas_core("Haswell", avx512, "Haswell").empty());       // the user's OPENBLAS_CORETYPE
  CHECK(better_openblas_core("Haswell", avx2, nullptr).empty());
  CHECK(better_openblas_core("Prescott", partial, nullptr).empty());
  CHECK(better_openblas_core("", avx512, nullptr).empty());  // not OpenBLAS
}

TEST_CASE("under oneDNN's AVX2 cap OpenBLAS gets its AVX2 kernels, whatever it chose", "[precision][blas]") {
  const auto avx512 =
      parse_cpuinfo("model name : X\nflags : fpu avx2 fma avx512f avx512cd avx512bw avx512dq avx512vl\n");
  const auto capped = with_onednn_isa(avx512, 0x7);  // dnnl_cpu_isa_avx2
  REQUIRE(capped.onednn_capped);
  CHECK(better_openblas_core("SkylakeX", capped, nullptr) == "Haswell");
  CHECK(better_openblas_core("Prescott", capped, nullptr) == "Haswell");  // a CPU OpenBLAS predates
  CHECK(better_openblas_core("Haswell", capped, nullptr).empty());
  CHECK(better_openblas_core("Zen", capped, nullptr).empty());
  CHECK(better_openblas_core("Prescott", capped, "Prescott").empty());  // the user's OPENBLAS_CORETYPE
}

TEST_CASE("the CLI runs OpenBLAS on the kernels chosen for this CPU and says which", "[precision][blas][cli]") {
  const std::string row = "bench --rows peak_gemm_fp32 --repeats 1 --warmup 0 --threads 1";
  const auto chosen = test::run_shell("env -u OPENBLAS_CORETYPE " + std::string(FLATNET_BINARY) + " " + row);
  REQUIRE(chosen.code == 0);
  if (openblas_core().empty()) {
    CHECK_THAT(chosen.output, Contains("blas: not OpenBLAS"));
  } else if (cpu_features().avx512_core) {
    CHECK_THAT(chosen.output, Contains("blas: OpenBLAS SkylakeX") || Contains("blas: OpenBLAS SapphireRapids"));
  } else if (cpu_features().onednn_capped) {  // ONEDNN_MAX_CPU_ISA=AVX2 on an AVX-512 CPU: the AVX2 kind
    CHECK_THAT(chosen.output, Contains("blas: OpenBLAS Haswell"));
  } else {
    CHECK_THAT(chosen.output, !Contains("set by flatnet"));
  }
  const auto user = test::run_shell("OPENBLAS_CORETYPE=Haswell " + std::string(FLATNET_BINARY) + " " + row);
  REQUIRE(user.code == 0);
  if (!openblas_core().empty()) CHECK_THAT(user.output, Contains("blas: OpenBLAS Haswell\n"));
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
    {
      AutocastGuard inner(false);
      CHECK(at::autocast::is_cpu_enabled());
    }
  }
  CHECK_FALSE(at::autocast::is_cpu_enabled());
}

namespace {
// A tiny inversion + U-Net generator (20x24 planes -> 16x16), seeded.
Generator tiny_generator(uint64_t seed, int64_t width) {
  torch::manual_seed(seed);
  GeneratorOptions o;
  o.rows = 20, o.cols = 24, o.scene = 16;
  o.inversion.phil = torch::randn({20, 16, 1}) * 0.2;
  o.inversion.phir = torch::randn({24, 16, 1}) * 0.2;
  o.unet.width = width;
  return Generator(o);
}
}  // namespace

TEST_CASE("a short bf16 autocast training run tracks the fp32 loss curve", "[precision][bf16]") {
  // The same tiny generator, data and optimiser, once in fp32 and once with the enhancer under
  // bf16 autocast (master weights and Adam in fp32): the curves must agree within bf16's noise.
  auto run = [](bool bf16) {
    auto g = tiny_generator(21, 4);
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

TEST_CASE("bf16 GEMM operands: products of the rounded operands, fp32 results and gradients, refused without bf16",
          "[precision][bf16][onednn]") {
  torch::manual_seed(11);
  const auto a0 = torch::randn({3, 40, 30}), b0 = torch::randn({1, 30, 20});
  if (!cpu_features().native_bf16()) {
    CHECK_THROWS_WITH(onednn_bmm(a0, b0, GemmOperands::bf16), Contains("bf16 operands need"));
    return;
  }
  auto rounded = [](const torch::Tensor& t) { return t.to(torch::kBFloat16).to(torch::kFloat32); };
  const auto weights = torch::randn({3, 40, 20});  // a loss that weighs every output differently
  auto a = a0.clone().requires_grad_(), b = b0.clone().requires_grad_();
  const auto c = onednn_matmul_autograd(a, b, GemmOperands::bf16);
  CHECK(c.scalar_type() == torch::kFloat32);
  // The product of the bf16-rounded operands, accumulated in fp32 (not rounded again), and not fp32's.
  const auto expected = torch::matmul(rounded(a0), rounded(b0));
  CHECK(torch::allclose(c, expected, 1e-4, 1e-4));
  CHECK_FALSE(torch::allclose(c, torch::matmul(a0, b0), 1e-4, 1e-4));
  (c * weights).sum().backward();
  // Gradients: the incoming gradient and the other operand rounded to bf16, summed in fp32; fp32 out.
  const auto g = rounded(weights);
  REQUIRE(a.grad().scalar_type() == torch::kFloat32);
  REQUIRE(b.grad().scalar_type() == torch::kFloat32);
  CHECK(torch::allclose(a.grad(), torch::matmul(g, rounded(b0).transpose(1, 2)), 1e-4, 1e-4));
  CHECK(torch::allclose(b.grad(), torch::matmul(rounded(a0).transpose(1, 2), g).sum(0, true), 1e-4, 1e-4));
}

TEST_CASE("bf16 training rounds the first stage's operands only, within a fraction of the picture's detail",
          "[precision][bf16]") {
  // The shipped simulation model's first stage on a golden capture: fp32 against the bf16 operands
  // that bf16 training uses where the CPU runs bf16 natively (fp32 accumulation and output).
  const auto model_path = test::source_dir() / "models" / "flatnet-sim-transpose.flatnet";
  auto model = load_model_file(model_path);
  auto& g = model.generator;
  const auto planes =
      load_capture(test::data_dir() / "golden" / "inet_n02980441_castle_raw.png", model.camera.raw).planes.unsqueeze(0);
  torch::NoGradGuard no_grad;
  const auto fp32 = g->first_stage(planes);  // {1,4,256,256}
  g->set_autocast_bf16(true);
  const auto mixed = g->first_stage(planes);
  g->set_autocast_bf16(false);
  CHECK(torch::equal(g->first_stage(planes), fp32));  // off again: fp32 exactly
  if (!cpu_features().native_bf16()) {
    CHECK(torch::equal(mixed, fp32));  // no native bf16: the first stage stays fp32
    return;
  }
  CHECK(mixed.scalar_type() == torch::kFloat32);
  CHECK_FALSE(torch::equal(mixed, fp32));
  // The error against the picture's own variation (its detail and contrast), plane by plane.
  for (int64_t c = 0; c < 4; ++c) {
    const auto reference = fp32[0][c], error = mixed[0][c] - reference;
    const double ratio = error.pow(2).mean().sqrt().item<double>() / reference.std().item<double>();
    INFO("plane " << c << ": rms error / std " << ratio);
    CHECK(ratio < 0.005);
  }
}

TEST_CASE("oneDNN convolutions (prepacked weights, fused bias and ReLU) compute the convolution",
          "[precision][bf16][onednn][solo]") {
  if (!cpu_features().onednn_bf16)
    SKIP_TEST("oneDNN has no bf16 convolution on " + cpu_features().onednn_isa + " (" + cpu_features().summary() +
              "); it needs AVX-512");
  // bf16 inputs and weights, so the reference sees exactly the values oneDNN sees; only the
  // accumulation and the output's rounding to bf16 differ.
  torch::manual_seed(3);
  for (const int64_t stride : {1, 2})
    for (const bool relu : {false, true}) {
      const auto x = torch::randn({2, 8, 12, 10}).to(torch::kBFloat16);
      const auto w = (torch::randn({16, 8, 3, 3}) * 0.2).to(torch::kBFloat16), b = torch::randn({16});
      OneDnnConv conv(w, b, {stride, 1, relu});
      const auto got = conv(x);
      auto expected = torch::conv2d(x.to(torch::kFloat32), w.to(torch::kFloat32), b, stride, 1);
      if (relu) expected = torch::relu(expected);
      INFO("stride " << stride << " relu " << relu);
      CHECK(got.sizes() == expected.sizes());
      CHECK(got.scalar_type() == torch::kBFloat16);
      CHECK(got.is_contiguous(at::MemoryFormat::ChannelsLast));
      CHECK((got.to(torch::kFloat32) - expected).abs().max().item<double>() <=
            0.01 * expected.abs().max().item<double>());
      if (relu) CHECK(got.min().item<double>() >= 0);
      CHECK(torch::equal(conv(x), got));  // the cached plan gives the same answer
    }
  OneDnnConv conv(torch::randn({4, 3, 3, 3}), torch::Tensor(), {1, 1, false});
  CHECK_THROWS_WITH(conv(torch::randn({1, 5, 8, 8})), Contains("{B,3,H,W}"));
}

TEST_CASE("bf16 inference with the onednn lever agrees with LibTorch's bf16 path and with fp32",
          "[precision][bf16][onednn]") {
  auto make = [] {
    auto g = tiny_generator(8, 8);
    g->train();
    torch::NoGradGuard no_grad;
    g->forward(torch::randn({2, 4, 20, 24}) * 0.1);  // batch-norm statistics
    return g;
  };
  auto fp32 = make(), libtorch_bf16 = make(), onednn_bf16 = make();
  fp32->prepare_inference(parse_inference_levers("fold,channels-last,gemm-up"));
  const auto before = OneDnnConv::built();
  libtorch_bf16->prepare_inference(parse_inference_levers("fold,channels-last,gemm-up,bf16"));
  CHECK(OneDnnConv::built() == before);
  onednn_bf16->prepare_inference(parse_inference_levers("fold,channels-last,gemm-up,bf16,onednn"));
  // Where oneDNN has no bf16 kernels the lever stands down: LibTorch's own bf16 path runs instead.
  const int64_t lever_convs = cpu_features().onednn_bf16 ? 19 : 0;  // 9 double convolutions + the output one
  CHECK(OneDnnConv::built() == before + lever_convs);
  c10::InferenceMode guard;
  const auto Y = torch::randn({2, 4, 20, 24}) * 0.1;
  const auto a = fp32->forward(Y), b = libtorch_bf16->forward(Y), c = onednn_bf16->forward(Y);
  CHECK(c.sizes() == a.sizes());
  CHECK(c.scalar_type() == torch::kFloat32);
  // The same kernels and the same bf16 bias: the fused ReLU commutes with the rounding, so the
  // result is LibTorch's bf16 result to the bit; against fp32 it differs by bf16's rounding.
  CHECK(torch::equal(b, c));
  CHECK((c - a).abs().max().item<double>() < 0.03);
  CHECK((c - a).abs().mean().item<double>() < 0.005);
}
