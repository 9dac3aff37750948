// Hostile inputs, sixth round (issue 113): the data-consistency step (a blur that underflows or reaches
// past the scene, a blur where no step runs, the step's origin through averaging and fine-tuning),
// the scene light (a camera file flatnet would refuse to read), few-pair calibrations (too few steps
// to judge, a shift search that ends at its range's edge), compressed and v7.3 .mat files that claim
// more than the camera needs, captures clipped by a bright light unit, and `train --force` that would
// stop halfway. Each case failed before its fix.
#include "catch_torch.hpp"

#include <cmath>

#include "consistency_bench.hpp"
#include "core/error.hpp"
#include "helpers.hpp"
#include "io/camera_config.hpp"
#include "io/config.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "io/safetensors.hpp"
#include "nn/model_file.hpp"
#include "optics/calibrate_dataset.hpp"
#include "optics/camera.hpp"
#include "optics/shift_structure.hpp"
#include "recon/data_consistency.hpp"
#include "recon/reconstructor.hpp"
#include "tiny_model.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;
using ::test::q;
using ::test::read_file;
using ::test::write_file;

namespace {

// A tiny model file (16-pixel scenes), with the data-consistency step in its spec when `strength` > 0
// (as a training with model.consistency writes it).
std::filesystem::path tiny_model_file(const std::filesystem::path& path, double strength = 0) {
  auto camera = ::test::tiny_camera();
  camera.name = "tiny";
  std::vector<std::string> sets = {"model.unet.width=2", "model.inversion.init=random"};
  if (strength > 0) sets.push_back("model.consistency.strength=" + std::to_string(strength));
  const auto config = Config::load({}, sets);
  Generator g(generator_options(config, camera, false));
  save_model_file(path, g, config, camera);
  return path;
}

// Three 128x160 captures and 32-pixel references for the tiny camera (tests/data/cameras/tiny.yaml),
// listed in `dir`/captures.txt and references.txt; the calibrate command line that reads them.
std::string tiny_lists(const std::filesystem::path& dir) {
  auto gen = at::detail::createCPUGenerator(5);
  std::string c, r;
  for (int i = 1; i <= 3; ++i) {
    write_gray16(dir / ("c" + std::to_string(i) + ".png"), (at::rand({128, 160}, gen) * 900 + 60).to(torch::kInt32));
    write_rgb8(dir / ("r" + std::to_string(i) + ".png"), at::rand({3, 32, 32}, gen));
    c += "c" + std::to_string(i) + ".png\n";
    r += "r" + std::to_string(i) + ".png\n";
  }
  write_file(dir / "captures.txt", c);
  write_file(dir / "references.txt", r);
  return "calibrate --meas-list " + q(dir / "captures.txt") + " --gt-list " + q(dir / "references.txt");
}

std::string tiny_camera_flag() { return " --camera " + q(::test::data_dir() / "cameras" / "tiny.yaml"); }

bool holds_files(const std::filesystem::path& dir) {
  return std::filesystem::exists(dir) && !std::filesystem::is_empty(dir);
}

}  // namespace

TEST_CASE("the data-consistency blur: far below a pixel it is the identity, past the scene it is refused",
          "[safe][hostile][consistency]") {
  flatnet::test::SmallCamera b(7);
  auto gen = at::detail::createCPUGenerator(3);
  const auto picture = at::rand({1, 3, flatnet::test::kBenchScene, flatnet::test::kBenchScene}, gen);
  const auto X = rgb_to_bayer_planes(srgb_to_linear(picture)).to(torch::kFloat64);
  const auto capture = torch::matmul(torch::matmul(b.calib.P, X), b.calib.Q.transpose(1, 2)).to(torch::kFloat32);
  const auto unblurred = DataConsistency(b.calib, b.camera, {10.0, 0.0})(capture * 1.3, picture * 0.5);
  for (const double sigma : {1e-30, 1e-300, 1e-3}) {
    INFO("sigma " << sigma);
    const auto out = DataConsistency(b.calib, b.camera, {10.0, sigma})(capture * 1.3, picture * 0.5);
    REQUIRE(torch::isfinite(out).all().item<bool>());  // 2 sigma^2 underflowed and the kernel was NaN
    CHECK(torch::allclose(out, unblurred, 1e-5, 1e-6));
  }
  // 16-pixel scenes hold a 3-sigma reach of 15 pixels: sigma 5 at most.
  CHECK(largest_consistency_blur(flatnet::test::kBenchScene) == Approx(5.0));
  CHECK_NOTHROW(DataConsistency(b.calib, b.camera, {10.0, 5.0}));
  CHECK_THROWS_WITH(DataConsistency(b.calib, b.camera, {10.0, 5.01}),
                    Contains("consistency_blur") && Contains("16-pixel scenes"));
  CHECK_THROWS_WITH(DataConsistency(b.calib, b.camera, {10.0, 64.0}), Contains("16-pixel scenes"));
}

TEST_CASE("a data-consistency blur where no step runs is refused by infer, export and train alike",
          "[safe][hostile][consistency][cli]") {
  // infer: the model applies no step and --data-consistency is off or not given.
  ReconstructorSpec spec;
  spec.consistency_blur = 5;
  ModelSpec plain;
  CHECK_THROWS_WITH(consistency_of(spec, plain), Contains("consistency_blur") && Contains("no step runs"));
  spec.data_consistency = 0;  // off
  CHECK_THROWS_WITH(consistency_of(spec, plain), Contains("consistency_blur"));
  spec.data_consistency = 10;
  CHECK(consistency_of(spec, plain).blur == 5);
  ModelSpec stepped;
  stepped.consistency_strength = 10;
  spec.data_consistency = ReconstructorSpec::kModelsOwn;
  CHECK(consistency_of(spec, stepped).blur == 5);  // the model's own step, blurred as asked
  spec.consistency_blur = 0;
  spec.data_consistency = 0;
  CHECK_NOTHROW(consistency_of(spec, plain));  // no blur: nothing to refuse

  ::test::Scratch s("round6_blur_without_step");
  const auto model = tiny_model_file(s.dir / "m.flatnet");
  const auto out = s.dir / "out.flatnet";
  const std::vector<std::pair<std::string, std::vector<std::string>>> refused = {
      {" --data-consistency off --consistency-blur 5", {"--consistency-blur", "no step"}},
      {" --data-consistency 10 --consistency-blur model", {"--consistency-blur: takes a number"}},
      {" --data-consistency 10 --consistency-blur 6", {"--consistency-blur", "16-pixel scenes"}},
      {" --data-consistency 10 --consistency-blur 64", {"--consistency-blur", "16-pixel scenes"}},
  };
  for (const auto& [flags, words] : refused) {
    INFO(flags);
    const auto r = ::test::run_flatnet("export --model " + q(model) + " --out " + q(out) + flags);
    CHECK(r.code == 2);
    for (const auto& w : words) CHECK_THAT(r.output, Contains(w));
    CHECK_FALSE(std::filesystem::exists(out));
  }
  // A blur far below a pixel is the identity, and writes a model infer can run; a subnormal one
  // (1e-320) is a number too (std::stod threw "stod" on it).
  for (const char* blur : {"1e-30", "1e-320"}) {
    std::filesystem::remove(out);
    const auto r = ::test::run_flatnet("export --model " + q(model) + " --out " + q(out) +
                                       " --data-consistency 10 --consistency-blur " + blur);
    INFO(r.output);
    CHECK(r.code == 0);
  }

  // train: a blur at strength 0, and a blur past the camera's 32-pixel scenes, before anything is written.
  const std::vector<std::pair<std::string, std::string>> runs = {
      {"--set loss.perceptual=0 --set model.consistency.blur=5", "model.consistency.strength"},
      {"--set data.camera=" + (::test::data_dir() / "cameras" / "tiny.yaml").string() +
           " --set loss.perceptual=0 --set model.consistency.strength=10 --set model.consistency.blur=64",
       "32-pixel scenes"},
  };
  for (const auto& [flags, words] : runs) {
    INFO(flags);
    const auto dir = s.dir / "run";
    const auto t = ::test::run_flatnet("train --out " + q(dir) + " " + flags);
    CHECK(t.code == 2);
    CHECK_THAT(t.output, Contains("model.consistency.blur") && Contains(words));
    CHECK_FALSE(holds_files(dir));
  }
}

TEST_CASE("the data-consistency step's origin survives averaging, refuses a mixed average and is told right",
          "[safe][hostile][consistency][model]") {
  ::test::Scratch s("round6_step_origin");
  const auto plain = tiny_model_file(s.dir / "plain.flatnet");
  const auto trained = tiny_model_file(s.dir / "trained.flatnet", 10);
  CHECK(load_model_file(trained).provenance.consistency == kConsistencyTrained);
  CHECK(load_model_file(plain).provenance.consistency.empty());
  for (const char* name : {"a.flatnet", "b.flatnet"}) {
    const auto r =
        ::test::run_flatnet("export --model " + q(plain) + " --data-consistency 10 --out " + q(s.dir / name));
    INFO(r.output);
    REQUIRE(r.code == 0);
    CHECK(load_model_file(s.dir / name).provenance.consistency == kConsistencySetAtExport);
  }
  // Two models whose step was set at export: their mean says so.
  auto r = ::test::run_flatnet("export --average-of " + q(s.dir / "a.flatnet") + "," + q(s.dir / "b.flatnet") +
                               " --out " + q(s.dir / "mean.flatnet"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  const auto mean = load_model_file(s.dir / "mean.flatnet");
  CHECK(mean.provenance.consistency == kConsistencySetAtExport);
  CHECK_THAT(mean.provenance.source, Contains("mean of 2 models") && Contains("set at export, not trained with"));
  r = ::test::run_flatnet("info " + q(s.dir / "mean.flatnet"));
  CHECK_THAT(r.output, Contains("set at export"));
  // One trained with the step, one whose step was set at export: the same spec, not the same model.
  r = ::test::run_flatnet("export --average-of " + q(trained) + "," + q(s.dir / "a.flatnet") + " --out " +
                          q(s.dir / "mixed.flatnet"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("a.flatnet") && Contains("set at export") && Contains("trained with"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "mixed.flatnet"));
  // An empty name in the list is named as such.
  r = ::test::run_flatnet("export --average-of " + q(s.dir / "a.flatnet") + ",," + q(s.dir / "b.flatnet") + " --out " +
                          q(s.dir / "x.flatnet"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--average-of") && Contains("empty name"));
  // A file from before the origin was recorded: its source text says it.
  auto file = read_safetensors(s.dir / "a.flatnet");
  file.metadata.erase("consistency");
  write_safetensors(s.dir / "legacy.flatnet", file.tensors, file.metadata);
  CHECK(load_model_file(s.dir / "legacy.flatnet").provenance.consistency == kConsistencySetAtExport);
  // An origin flatnet never writes is refused, naming the file.
  file.metadata["consistency"] = "learned\nsomewhere";
  write_safetensors(s.dir / "forged.flatnet", file.tensors, file.metadata);
  CHECK_THROWS_WITH(load_model_file(s.dir / "forged.flatnet"), Contains("forged.flatnet") && Contains("consistency"));
  // A step whose blur reaches past the file's own 16-pixel scenes (inside model_spec's 0-64): refused
  // as the file is read, naming it, not later as an internal error.
  auto stepped = read_safetensors(trained);
  auto& spec_text = stepped.metadata["model_spec"];
  const auto at = spec_text.find("blur: 0");
  REQUIRE(at != std::string::npos);
  spec_text.replace(at, 7, "blur: 64");
  write_safetensors(s.dir / "reach.flatnet", stepped.tensors, stepped.metadata);
  CHECK_THROWS_WITH(load_model_file(s.dir / "reach.flatnet"), Contains("reach.flatnet") && Contains("16-pixel scenes"));
}

TEST_CASE("train --force checks everything it would remove before it removes anything", "[safe][hostile][train]") {
  ::test::Scratch s("round6_force_folder");
  const auto run = s.dir / "run";
  std::filesystem::create_directories(run / "kept" / "step6.flatnet");
  write_file(run / "kept" / "step6.flatnet" / "notes.txt", "a user's file in a folder named like a kept model");
  write_file(run / "latest.ckpt", "the old run's checkpoint");
  write_file(run / "log.csv", "step,loss\n");
  const auto r = ::test::run_flatnet("train --out " + q(run) + " --force --set train.iterations=1");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("step6.flatnet") && Contains("is a folder"));
  CHECK(read_file(run / "latest.ckpt") == "the old run's checkpoint");  // nothing removed
  CHECK(std::filesystem::exists(run / "log.csv"));
  CHECK(std::filesystem::exists(run / "kept" / "step6.flatnet" / "notes.txt"));
}

TEST_CASE("calibrate refuses flags that would do nothing, too few steps to judge, and captures of another size",
          "[safe][hostile][calibrate]") {
  ::test::Scratch s("round6_calibrate_flags");
  const auto lists = tiny_lists(s.dir);
  const auto out = " --out " + q(s.dir / "cal" / "calib.mat");
  const std::vector<std::pair<std::string, std::vector<std::string>>> cases = {
      // A calibration from display captures has no light unit to set, and no references' settings.
      {lists + tiny_camera_flag() + " --scene-light 0.5", {"--scene-light", "--references"}},
      {lists + tiny_camera_flag() + " --reference-order bgr", {"--reference-order", "--references"}},
      {lists + tiny_camera_flag() + " --compact", {"--compact", "--references"}},
      // --white-light states the white capture's light: without one it did nothing.
      {lists + tiny_camera_flag() + " --references --white-light 0.5", {"--white-light", "--white-capture"}},
      // Two steps end before the shift structure is judged.
      {lists + tiny_camera_flag() + " --iterations 2", {"--iterations", "at least 4"}},
  };
  for (const auto& [command, words] : cases) {
    INFO(command);
    const auto r = ::test::run_flatnet(command + out);
    CHECK(r.code == 2);
    for (const auto& w : words) CHECK_THAT(r.output, Contains(w));
    CHECK_FALSE(holds_files(s.dir / "cal"));
  }
  // A geometry inside every range whose raw frame is not the captures' size: both sizes named at once.
  write_file(s.dir / "big.yaml",
             "name: big\nraw_height: 1024\nraw_width: 1280\nadc_bits: 10\ncrop: [2, 2, 60, 76]\n"
             "centring: plane\nscene_size: 32\n");
  const auto r = ::test::run_flatnet(lists + " --camera " + q(s.dir / "big.yaml") + out);
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("c1.png") && Contains("160x128") && Contains("1280x1024"));
  // The library judges the same: steps that end before the verdict are refused.
  DatasetCalibrationOptions o;
  o.iterations = 3;
  o.progress = false;
  const auto pair = [](int64_t) { return CapturePair{torch::ones({4, 8, 8}), torch::ones({4, 4, 4}), {}}; };
  CHECK_THROWS_WITH(calibrate_from_pairs(2, pair, 8, 8, 4, o), Contains("free_passes + 2"));
}

TEST_CASE("a camera file is read back before it is written: one flatnet would refuse is never written",
          "[safe][hostile][calibrate]") {
  auto camera = load_camera_config(::test::data_dir() / "cameras" / "tiny.yaml");
  const auto text = camera_file_text(camera, "calib.mat", "# made here\n", "camera.yaml");
  CHECK_THAT(text, Contains("# made here") && Contains("calibration: \"calib.mat\""));
  CHECK(camera_from_yaml_text(text, "camera.yaml").tikhonov_lambda == camera.tikhonov_lambda);
  camera.tikhonov_lambda = 939189;  // --scene-light 1e-6's light unit
  CHECK_THROWS_WITH(camera_file_text(camera, "calib.mat", "", "camera.yaml"),
                    Contains("camera.yaml") && Contains("tikhonov_lambda"));
  camera.tikhonov_lambda = INFINITY;  // --scene-light 1e-300's
  CHECK_THROWS_WITH(camera_file_text(camera, "calib.mat", "", "camera.yaml"), Contains("tikhonov_lambda"));
}

TEST_CASE("a calibration .mat may claim no more than its camera needs: compressed, v7.3 and damaged v7.3 files",
          "[safe][hostile][mat]") {
  ::test::Scratch s("round6_mat_claims");
  const auto camera = load_camera_config(::test::data_dir() / "cameras" / "tiny.yaml");  // 60x76 crop, 32-px scenes
  // 32 MB of zeros compresses to a few tens of kilobytes: refused as it inflates past what the camera needs.
  write_mat(s.dir / "bomb.mat", {{"P1b", torch::zeros({2000, 2000}, torch::kFloat64)}});
  REQUIRE(std::filesystem::file_size(s.dir / "bomb.mat") < 200000);
  CHECK_THROWS_WITH(load_calibration(s.dir / "bomb.mat", camera), Contains("bomb.mat") && Contains("inflates past"));
  // A v7.3 (HDF5) variable's claim is checked before it is read.
  write_mat(s.dir / "big73.mat", {{"P1b", torch::zeros({2000, 1000}, torch::kFloat64)}}, MatVersion::v73);
  CHECK_THROWS_WITH(load_calibration(s.dir / "big73.mat", camera),
                    Contains("big73.mat") && Contains("P1b") && Contains("2000x1000") && Contains("allows"));
  // 1,912 bytes whose P1b claims 1 GiB (chunks never stored, read as HDF5's fill value): refused from
  // its claim by any reader, before matio allocates it (tests/data/hostile/make_v73_claim.c).
  const auto claim = ::test::data_dir() / "hostile" / "v73_claims_1gb.mat";
  CHECK_THROWS_WITH(MatReader(claim).read("P1b"), Contains("v73_claims_1gb.mat") && Contains("32768x4096"));
  CHECK_THROWS_WITH(load_calibration(claim, camera), Contains("v73_claims_1gb.mat") && Contains("32768x4096"));
  // A v7.3 header before a damaged HDF5 body: the file is named damaged, not as missing a variable.
  std::map<std::string, torch::Tensor> vars;
  for (const char* c : {"b", "gb", "gr", "r"}) {
    vars[std::string("P1") + c] = torch::rand({60, 32}, torch::kFloat64) - 0.5;
    vars[std::string("Q1") + c] = torch::rand({76, 32}, torch::kFloat64) - 0.5;
  }
  write_mat(s.dir / "good73.mat", vars, MatVersion::v73);
  CHECK_NOTHROW(load_calibration(s.dir / "good73.mat", camera));
  auto bytes = read_file(s.dir / "good73.mat");
  for (size_t i = 520; i < bytes.size(); ++i) bytes[i] = static_cast<char>(0xa5);  // the HDF5 body, after its signature
  write_file(s.dir / "damaged73.mat", bytes);
  CHECK_THROWS_WITH(load_calibration(s.dir / "damaged73.mat", camera),
                    Contains("damaged73.mat") && Contains("damaged") && !Contains("file has: )"));
}

TEST_CASE("simulate says when most captures clip, and names the setting that fixes it", "[hostile][simulate]") {
  ::test::Scratch s("round6_clipped");
  const auto photos = ::test::make_photos(s.dir / "photos");
  auto r = ::test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "bright") +
                               " --exposure 60 --noise off --workers 1");
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("2 of 2 captures") && Contains("full scale") && Contains("--exposure"));
  r = ::test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "plain") +
                          " --noise off --workers 1");
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, !Contains("full scale"));
}

// A camera whose rows are a moving shadow and whose columns are random, seen in few pairs: the
// column search drifted to the top of its range, and the verdict kept a structure it did not find.
TEST_CASE("a shift search that ends at its range's edge is no finding: the structure is rejected",
          "[optics][calibrate][hostile]") {
  constexpr int64_t rows = 48, cols = 56, n = 16;
  auto gen = at::detail::createCPUGenerator(11);
  auto code = ((at::rand({4, rows + 32}, gen) < 0.5).to(torch::kFloat64) * 2 - 1);
  code = 0.25 * code.roll(1, 1) + 0.5 * code + 0.25 * code.roll(-1, 1);
  const auto P = shift_factor(code, rows, n, -1.7, 1.0);
  auto Q = at::randn({4, cols, n}, gen).to(torch::kFloat64);
  Q -= Q.mean(1, true);
  const auto load = [&](int64_t i) {
    auto g = at::detail::createCPUGenerator(5000 + static_cast<uint64_t>(i));
    const auto X = at::rand({4, n, n}, g).to(torch::kFloat64);
    auto Y = torch::matmul(torch::matmul(P, X), Q.transpose(1, 2));
    Y = Y + 0.5 * Y.std().item<double>() * at::randn(Y.sizes(), g).to(torch::kFloat64);
    return CapturePair{Y.to(torch::kFloat32), X.to(torch::kFloat32), {}};
  };
  DatasetCalibrationOptions o;
  o.progress = false;
  o.iterations = 12;
  const auto fit = calibrate_from_pairs(12, load, rows, cols, n, o);
  INFO("searched " << fit.searched_shifts[0] << " " << fit.searched_shifts[1] << ", explains " << fit.structure_explains
                   << ", edge " << fit.shift_at_edge[0] << fit.shift_at_edge[1]);
  CHECK(fit.searched_shifts[0] == Approx(-1.7).margin(0.02));  // the rows' shadow is found
  CHECK_FALSE(fit.shift_at_edge[0]);
  // The columns' search drifted to the top of its range (7.7 of 8), and the share alone would have kept it.
  CHECK(fit.shift_at_edge[1]);
  CHECK(std::abs(fit.searched_shifts[1]) > 7);
  CHECK(fit.structure_explains > kStructureExplainsAtLeast);
  CHECK(fit.structure_rejected);
  CHECK(fit.shift_cols == 0);
}
