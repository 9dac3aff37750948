// The generator spec (nn/model_spec): typed rows, what model files store, how older files convert,
// and model files that stand alone (no configs folder, no training defaults).
#include "catch_torch.hpp"

#include "core/error.hpp"
#include "helpers.hpp"
#include "io/safetensors.hpp"
#include "nn/model_file.hpp"
#include "nn/model_spec.hpp"
#include "tiny_model.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

TEST_CASE("a model spec reads back from its YAML as it was written", "[model][config]") {
  const auto config =
      Config::load({}, {"model.enhancer=nafnet", "model.nafnet.width=8", "model.nafnet.dec_blocks=2",
                        "model.inversion.init=calibfree", "model.inversion.slope=1.887", "model.bn_momentum=0.1",
                        "model.level_input=true", "model.inversion.shared=false", "model.inversion.seed=7"});
  const auto spec = model_spec(config);
  CHECK(spec.enhancer == "nafnet");
  CHECK(spec.nafnet.width == 8);
  CHECK(spec.nafnet.dec_blocks == 2);
  CHECK(spec.inversion_slope == 1.887);
  CHECK(spec.bn_momentum == 0.1);
  CHECK(spec.level_input);
  CHECK_FALSE(spec.inversion_shared);
  CHECK(spec.inversion_seed == 7);
  const auto text = model_spec_yaml(spec);
  CHECK_THAT(text, Contains("nafnet:") && Contains("slope: 1.887"));
  CHECK(text.find("train") == std::string::npos);  // the spec, not the training config
  const auto back = parse_model_spec(text, "m.flatnet", /*strict=*/true);
  CHECK(model_spec_yaml(back) == text);
  CHECK(back.inversion_slope == spec.inversion_slope);
  CHECK(back.bn_momentum == spec.bn_momentum);
}

TEST_CASE("a stored spec is checked row by row, naming the file and the key", "[model][config][safe]") {
  CHECK_THROWS_WITH(parse_model_spec("model:\n  unet:\n    width: 0\n", "f.flatnet", true),
                    Contains("f.flatnet") && Contains("model.unet.width") && Contains("1 to 4096"));
  CHECK_THROWS_WITH(parse_model_spec("model:\n  bn_momentum: nan\n", "f.flatnet", true),
                    Contains("f.flatnet") && Contains("model.bn_momentum"));
  CHECK_THROWS_WITH(parse_model_spec("model:\n  level_input: maybe\n", "f.flatnet", true),
                    Contains("model.level_input") && Contains("true or false"));
  CHECK_THROWS_WITH(parse_model_spec("model:\n  unet: [1, 2\n", "f.flatnet", true), Contains("f.flatnet"));
  // A key this flatnet does not know: refused in a stored spec (a newer file), skipped in an older
  // file's training config (a key it had and the spec dropped).
  CHECK_THROWS_WITH(parse_model_spec("model:\n  warp: 3\n", "f.flatnet", true),
                    Contains("f.flatnet") && Contains("model.warp") && Contains("newer"));
  CHECK_NOTHROW(parse_model_spec("model:\n  warp: 3\n", "old.flatnet", false));
}

TEST_CASE("an older file's training config converts to a spec: its other sections are a record", "[model][config]") {
  // A config from before model.level_input and model.nafnet existed, with training keys beside it
  // (one of them renamed since: a model file must not care).
  const std::string old =
      "model:\n  input: inversion\n  enhancer: unet\n  unet:\n    width: 32\n"
      "  inversion:\n    init: transpose\n    shared: true\n    channel: gb\n"
      "train:\n  batch: 8\n  renamed_key: 3\nloss:\n  mse: 1.0\n";
  const auto spec = parse_model_spec(old, "old.flatnet", /*strict=*/false);
  CHECK(spec.unet.width == 32);
  CHECK(spec.inversion_init == "transpose");
  CHECK_FALSE(spec.level_input);  // the default of a key the file predates
  CHECK(spec.nafnet.width == 16);
  CHECK(spec.bn_momentum == 0.99);
}

TEST_CASE("every model setting of the defaults file has one row, and a config out of range is refused at load",
          "[model][config]") {
  const auto config = Config::load({}, {});
  std::set<std::string> rows;
  for (const auto& f : model_spec_fields()) rows.insert(std::string("model.") + f.key);
  for (const auto& [key, value] : config.values())
    if (key.rfind("model.", 0) == 0) CHECK(rows.count(key) == 1);
  CHECK(rows.size() == model_spec_fields().size());
  CHECK_THROWS_WITH(Config::load({}, {"model.rcan.reduction=0"}),
                    Contains("model.rcan.reduction") && Contains("1 to 4096"));
}

TEST_CASE("the shipped models read without training defaults, and rewritten give the same pictures",
          "[model][shipped]") {
  test::Scratch s("shipped_spec");
  for (const auto* name : {"flatnet-sim-transpose", "flatnet-sim-calibfree"}) {
    INFO(name);
    const auto file = test::source_dir() / "models" / (std::string(name) + ".flatnet");
    auto m = load_model_file(file);
    CHECK(m.spec.unet.width == 32);
    CHECK(m.spec.level_input);
    // The calibration-free model's first stage starts from the transposes of a camera identified from its
    // training pairs (its card), with slower batch-norm statistics.
    CHECK(m.spec.bn_momentum == (std::string(name) == "flatnet-sim-transpose" ? 0.1 : 0.01));
    CHECK(m.spec.inversion_init == "transpose");
    CHECK(m.recorded("train.crop") == "128");
    CHECK(m.recorded("no.such.key").empty());
    // As written before the typed spec (the transpose model shipped until 2026-12-01 was such a file):
    // the embedded training config alone converts to the same spec.
    auto tensors = read_safetensors(file);
    REQUIRE(tensors.metadata.erase("model_spec") == 1);
    const auto legacy = s.dir / (std::string(name) + "-legacy.flatnet");
    write_safetensors(legacy, tensors.tensors, tensors.metadata);
    CHECK(model_spec_yaml(load_model_file(legacy).spec) == model_spec_yaml(m.spec));
    const auto again = s.dir / (std::string(name) + ".flatnet");
    save_model_file(again, m.generator, model_identity(m));
    auto r = load_model_file(again);
    CHECK(model_spec_yaml(r.spec) == model_spec_yaml(m.spec));
    CHECK(r.recipe == m.recipe);
    torch::NoGradGuard no_grad;
    const auto planes = torch::randn({1, 8, 500, 620}).narrow(1, 0, 4) * 0.1;  // {1,4,500,620}
    CHECK(torch::equal(m.generator->forward(planes), r.generator->forward(planes)));
  }
}

TEST_CASE("an installed flatnet whose configs folder is gone runs a shipped model", "[model][shipped][cli]") {
  test::Scratch s("no_configs");
  // The install layout (CMakeLists.txt: bin/flatnet, share/flatnet/models), without share/flatnet/configs.
  std::filesystem::create_directories(s.dir / "bin");
  std::filesystem::create_directories(s.dir / "share" / "flatnet" / "models");
  std::filesystem::copy_file(FLATNET_BINARY, s.dir / "bin" / "flatnet");
  const auto model = s.dir / "share" / "flatnet" / "models" / "flatnet-sim-transpose.flatnet";
  std::filesystem::copy_file(test::source_dir() / "models" / "flatnet-sim-transpose.flatnet", model);
  std::filesystem::create_directories(s.dir / "in");
  std::filesystem::copy_file(test::data_dir() / "golden" / "bsds_16052_raw.png", s.dir / "in" / "a.png");
  const auto r = test::run_shell("env -u FLATNET_DATA_DIR " + test::q(s.dir / "bin" / "flatnet") +
                                 " infer --threads 1 --model " + test::q(model) + " --input " + test::q(s.dir / "in") +
                                 " --out " + test::q(s.dir / "out") + " 2>&1");
  INFO(r.output);
  CHECK(r.code == 0);
  CHECK(std::filesystem::exists(s.dir / "out" / "a.png"));
  const auto info = test::run_shell("env -u FLATNET_DATA_DIR " + test::q(s.dir / "bin" / "flatnet") + " info " +
                                    test::q(model) + " 2>&1");
  INFO(info.output);
  CHECK(info.code == 0);
  CHECK_THAT(info.output, Contains("U-Net, width 32") && Contains("transpose init"));
}
