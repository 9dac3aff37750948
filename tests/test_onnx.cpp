// ONNX export (nn/onnx_export) and the OpenCV DNN engine (recon/opencv_engine): the graph passes
// ONNX's checker, OpenCV 4.6 imports it, and it computes what LibTorch computes.
#include "catch_torch.hpp"
#include <cstdlib>
#include <fstream>

#include <onnx/checker.h>

#include "core/error.hpp"
#include "helpers.hpp"
#include "io/raw.hpp"
#include "nn/model_file.hpp"
#include "nn/onnx_export.hpp"
#include "recon/opencv_engine.hpp"
#include "tiny_model.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

// A random tiny generator; Tikhonov's fixed filter (buffers, not parameters) is randomised too.
Generator variant(const std::vector<std::string>& sets, const CameraConfig& camera) {
  torch::manual_seed(5);  // the weights must not depend on what ran before in this process
  auto g = test::random_generator(Config::load({}, sets), camera);
  torch::NoGradGuard ng;
  for (auto& b : g->named_buffers())
    if (b.key().rfind("tikhonov.", 0) == 0) b.value().uniform_(-0.3, 0.3);
  return g;
}

// The generators both engine tests export: every first stage, with and without the light level,
// the measurement pre-processor, and the U-Net, DnCNN and NAFNet enhancers.
struct ExportCase {
  const char* what;
  std::vector<std::string> sets;
  CameraConfig camera;
};
std::vector<ExportCase> export_cases() {
  const auto plain = test::tiny_camera(), level = test::tiny_camera(Centring::level);
  return {
      {"inversion, one pair, U-Net", {"model.unet.width=4"}, plain},
      {"inversion, one pair per channel, light level, U-Net",
       {"model.unet.width=4", "model.inversion.shared=false", "model.level_input=true"},
       level},
      {"Tikhonov first stage, light level, U-Net",
       {"model.unet.width=4", "model.input=tikhonov", "model.level_input=true"},
       level},
      {"inversion, DnCNN", {"model.enhancer=dncnn", "model.dncnn.layers=4", "model.dncnn.width=3"}, plain},
      {"measurement pre-processor, inversion, light level, U-Net",
       {"model.unet.width=4", "model.preprocessor.width=3", "model.preprocessor.depth=3", "model.level_input=true"},
       level},
      {"inversion, light level, NAFNet",
       {"model.enhancer=nafnet", "model.nafnet.width=4", "model.level_input=true"},
       level},
  };
}

// Where scripts/setup.sh put onnxruntime-node (FLATNET_ORT_DIR in the environment wins).
std::filesystem::path onnxruntime_dir() {
  const char* env = std::getenv("FLATNET_ORT_DIR");
  return env && *env ? std::filesystem::path(env) : std::filesystem::path(FLATNET_ORT_DIR);
}

void write_f32(const std::filesystem::path& path, const torch::Tensor& t) {
  const auto c = t.contiguous().to(torch::kFloat32);
  std::ofstream(path, std::ios::binary).write(static_cast<const char*>(c.data_ptr()), c.numel() * 4);
}

// The model run in ONNX Runtime (tests/tools/onnxruntime_run.js under Node) on `input`.
torch::Tensor run_in_onnxruntime(const std::filesystem::path& model, const torch::Tensor& input,
                                 const std::filesystem::path& scratch) {
  const auto in = scratch / "in.f32", out = scratch / "out.f32";
  write_f32(in, input);
  std::string dims;
  for (auto d : input.sizes()) dims += (dims.empty() ? "" : ",") + std::to_string(d);
  const auto r = test::run_shell("NODE_PATH=" + test::q(onnxruntime_dir() / "node_modules") + " node " +
                                 test::q(test::source_dir() / "tests" / "tools" / "onnxruntime_run.js") + " " +
                                 test::q(model) + " " + test::q(in) + " " + dims + " " + test::q(out));
  INFO(r.output);
  REQUIRE(r.code == 0);
  const auto size = static_cast<int64_t>(std::filesystem::file_size(out));
  auto result = torch::empty({size / 4}, torch::kFloat32);
  std::ifstream(out, std::ios::binary).read(static_cast<char*>(result.data_ptr()), size);
  REQUIRE(r.output.find("\"dims\":[" + std::to_string(input.size(0)) + ",3,") != std::string::npos);
  return result;
}

}  // namespace

TEST_CASE("ONNX export has a batch axis: ONNX Runtime computes what LibTorch computes, batch 1 and 3",
          "[onnx][onnxruntime][solo]") {
  if (test::run_shell("command -v node").code != 0) SKIP_TEST("no node (scripts/setup.sh installs nodejs)");
  if (!std::filesystem::exists(onnxruntime_dir() / "node_modules" / "onnxruntime-node" / "package.json"))
    SKIP_TEST("no onnxruntime-node under " + onnxruntime_dir().string() + " (scripts/setup.sh installs it)");
  test::Scratch s("onnxruntime");
  const auto cases = export_cases();
  for (const auto& c : cases) {
    INFO(c.what);
    auto g = variant(c.sets, c.camera);
    const auto file = s.dir / "model.onnx";
    std::filesystem::remove(file);
    export_onnx(file, g, c.camera);
    for (int64_t batch : {1, 3}) {
      INFO("batch " << batch);
      torch::manual_seed(7 + batch);
      // Samples of different light levels, so a batch axis mixed up with another would show.
      const auto planes =
          torch::randn({batch, 4, 20, 24}) + torch::arange(batch, torch::kFloat32).view({batch, 1, 1, 1}) * 0.3;
      torch::Tensor expected;
      {
        torch::NoGradGuard ng;
        expected = g->forward(planes);  // {batch,3,16,16}
      }
      const auto flat = run_in_onnxruntime(file, planes, s.dir);
      REQUIRE(flat.numel() == expected.numel());
      const auto got = flat.view_as(expected);
      CHECK((got - expected).abs().max().item<double>() < 1e-4);
      // Each sample of the batch is the model run on that sample alone: a batch axis mixed up with
      // another, or samples that leak into each other, would break it. (Whether a random model's
      // outputs differ much between samples depends on its draw; CI once drew one whose did not.)
      for (int64_t i = 0; i < batch && batch > 1; ++i) {
        INFO("sample " << i);
        torch::NoGradGuard ng;
        const auto alone = g->forward(planes.slice(0, i, i + 1));  // {1,3,16,16}
        CHECK((got.slice(0, i, i + 1) - alone).abs().max().item<double>() < 1e-4);
      }
    }
  }
}

TEST_CASE("ONNX export: OpenCV DNN computes what LibTorch computes, for every first stage and enhancer", "[onnx]") {
  test::Scratch s("onnx");
  const auto cases = export_cases();
  for (const auto& c : cases) {
    INFO(c.what);
    auto g = variant(c.sets, c.camera);
    const auto file = s.dir / "model.onnx";
    std::filesystem::remove(file);
    const auto rep = export_onnx(file, g, c.camera);
    CHECK(rep.bytes == static_cast<int64_t>(std::filesystem::file_size(file)));
    CHECK_NOTHROW(onnx::checker::check_model(file.string()));  // the file as written, read back by ONNX

    OpenCvEngine engine(file);
    CHECK(engine.info().rows == 20);
    CHECK(engine.info().scene == 16);
    CHECK(engine.info().level_input == g->options().level_input);
    const auto camera = engine.camera();  // the preprocessing travels in the metadata
    CHECK(camera.raw.centring == c.camera.raw.centring);
    CHECK_NOTHROW(engine.check_camera(camera));

    torch::manual_seed(3);
    const auto planes = torch::randn({2, 4, 20, 24}) + (c.camera.raw.centring == Centring::level ? 0.7 : 0.0);
    torch::Tensor expected;
    {
      torch::NoGradGuard ng;
      expected = g->forward(planes);  // eval mode, batch norm not folded
    }
    const auto got = engine.forward(planes);
    REQUIRE(got.sizes() == expected.sizes());
    CHECK((got - expected).abs().max().item<double>() < 1e-4);
    CHECK(expected.std().item<double>() > 1e-3);  // a model whose output varies, so the match means something
  }
}

TEST_CASE("ONNX export refuses what it cannot express, and bad ONNX files are named", "[onnx][errors]") {
  test::Scratch s("onnx");
  const auto camera = test::tiny_camera();
  auto rcan = variant({"model.enhancer=rcan", "model.rcan.groups=1", "model.rcan.blocks=1", "model.rcan.width=4",
                       "model.rcan.reduction=2"},
                      camera);
  CHECK_THROWS_WITH(export_onnx(s.dir / "r.onnx", rcan, camera), Contains("RCAN"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "r.onnx"));

  auto g = variant({"model.unet.width=2"}, camera);
  CHECK_THROWS_WITH(export_onnx(s.dir / "l.onnx", g, test::tiny_camera(Centring::level)), Contains("level"));

  const auto junk = s.dir / "junk.onnx";
  std::ofstream(junk) << "not a protobuf at all \x01\x02\x03";
  CHECK_THROWS_WITH(OpenCvEngine(junk), Contains("junk.onnx") && Contains("not an ONNX model"));

  const auto good = s.dir / "good.onnx";
  export_onnx(good, g, camera);
  OpenCvEngine engine(good);
  CHECK_THROWS_WITH(engine.check_camera(test::tiny_camera(Centring::level)),
                    Contains("good.onnx") && Contains("level"));
  auto wrong_size = camera;
  wrong_size.scene_size = 32;
  CHECK_THROWS_WITH(engine.check_camera(wrong_size), Contains("good.onnx") && Contains("16x16"));

  // Truncated: half the bytes.
  const auto bytes = std::filesystem::file_size(good);
  std::filesystem::resize_file(good, bytes / 2);
  CHECK_THROWS_WITH(OpenCvEngine(good), Contains("good.onnx"));
}

TEST_CASE("the shipped models' ONNX graphs equal LibTorch on real and saturated captures, in both engines",
          "[onnx][shipped]") {
  const auto model_path = test::source_dir() / "models" / "flatnet-sim-calibfree.flatnet";
  const auto capture = test::data_dir() / "golden" / "bsds_16052_raw.png";
  auto m = load_model_file(model_path);
  test::Scratch s("onnx_shipped");
  const auto file = s.dir / "model.onnx";
  export_onnx(file, m.generator, m.camera);
  OpenCvEngine engine(file);
  const bool have_ort =
      test::run_shell("command -v node").code == 0 &&
      std::filesystem::exists(onnxruntime_dir() / "node_modules" / "onnxruntime-node" / "package.json");
  // A real capture, and a capture saturated everywhere (16 of the 250 held-out display captures are):
  // after the camera's centring its planes are constant, each at its light level.
  const auto real = load_capture(capture, m.camera.raw).planes.unsqueeze(0);  // {1,4,500,620}
  const auto saturated = torch::ones_like(real) * torch::tensor({0.9f, 1.0f, 1.0f, 0.8f}).view({1, 4, 1, 1});
  // Tolerances, measured: ONNX Runtime follows LibTorch to 4e-5 on the real capture. On the saturated
  // one the centred planes are rounding noise around zero (each plane minus its own mean), which
  // the engines' reductions round differently: 1e-2 there. OpenCV 4.6 runs 3x3 convolutions with
  // Winograd, which it cannot switch off before 4.7 (opencv/opencv#22577): up to 0.075 on single
  // pixels, while the mean difference stays under 1e-3 (5e-3 on the saturated capture).
  for (const auto& [what, planes, ort_tolerance, opencv_mean_tolerance] :
       {std::tuple<const char*, torch::Tensor, double, double>{"real", real, 1e-3, 1e-3},
        {"saturated", saturated, 2e-2, 5e-3}}) {
    INFO(what);
    torch::Tensor expected;
    {
      torch::NoGradGuard ng;
      m.generator->eval();
      expected = m.generator->forward(planes).clamp(0, 1);  // {1,3,256,256}, as an image shows it
    }
    CHECK(expected.std().item<double>() > 0.01);
    const auto opencv = engine.forward(planes).clamp(0, 1);
    CHECK((opencv - expected).abs().max().item<double>() < 0.1);
    CHECK((opencv - expected).abs().mean().item<double>() < opencv_mean_tolerance);
    if (have_ort) {
      const auto ort = run_in_onnxruntime(file, planes, s.dir).view_as(expected).clamp(0, 1);
      CHECK((ort - expected).abs().max().item<double>() < ort_tolerance);
    }
  }
}
