// Your own FlatCam (docs/own-camera.md), at a tiny scale: a camera known only from its display-capture
// pairs is calibrated from them (`calibrate --dataset`), a model trains on them, and `infer` says each
// capture fits that camera; captures of another camera are flagged, and --require-fit refuses them.
#include <cmath>
#include "catch_torch.hpp"

#include <cctype>
#include <fstream>

#include "core/util.hpp"
#include "helpers.hpp"
#include "io/camera_config.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "optics/calibrate.hpp"
#include "optics/camera.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;
using test::q;

namespace {

// A 32-pixel FlatCam in the geometry of tests/data/cameras/tiny.yaml (64x80 planes, a 60x76 window):
// binary masks with about half their features open, the sensor noise of the reference camera.
void write_tiny_rig(const std::filesystem::path& path, uint64_t seed) {
  auto gen = at::detail::createCPUGenerator(seed);
  std::map<std::string, torch::Tensor> vars;
  for (const char* c : {"b", "gb", "gr", "r"}) {
    vars[std::string("PhiL_") + c] = (at::rand({64, 32}, gen) > 0.5).to(torch::kFloat64) * 0.06;
    vars[std::string("PhiR_") + c] = (at::rand({80, 32}, gen) > 0.5).to(torch::kFloat64) * 0.06;
    vars[std::string("gain_") + c] = torch::full({1, 1}, 1.0, torch::kFloat64);
  }
  vars["vig_rows"] = torch::linspace(1e-4, 2e-4, 64, torch::kFloat64).view({1, 64});
  vars["vig_cols"] = torch::linspace(1e-4, 2e-4, 80, torch::kFloat64).view({1, 80});
  vars["full_well"] = torch::full({1, 1}, 40000.0, torch::kFloat64);
  vars["read_noise"] = torch::full({1, 1}, 4.0, torch::kFloat64);
  vars["dark"] = torch::full({1, 1}, 0.02, torch::kFloat64);
  vars["adc_bits"] = torch::full({1, 1}, 10.0, torch::kFloat64);
  write_mat(path, vars);
}

// The tiny geometry, plus what a camera file may add.
void write_camera(const std::filesystem::path& path, const std::string& extra) {
  std::ifstream in(test::data_dir() / "cameras" / "tiny.yaml");
  std::string text((std::istreambuf_iterator<char>(in)), {});
  std::ofstream(path) << text << extra;
}

}  // namespace

TEST_CASE("own camera: calibrate from the dataset, train, infer, and the camera fit says which captures fit",
          "[cli][own-camera]") {
  test::Scratch s("own_camera");
  // The physical camera (its rig stands in for the world) and another one.
  for (const auto& [name, seed] : std::vector<std::pair<std::string, uint64_t>>{{"truth", 1}, {"other", 2}}) {
    std::filesystem::create_directories(s.dir / name);
    write_tiny_rig(s.dir / name / "rig.mat", seed);
    write_camera(s.dir / name / "camera.yaml", "rig: rig.mat\n");
  }
  write_camera(s.dir / "geometry.yaml", "");  // what the user knows: the sensor's geometry alone
  const auto photos = s.dir / "photos";
  std::filesystem::create_directories(photos);
  auto gen = at::detail::createCPUGenerator(9);
  for (int i = 0; i < 96; ++i)  // random pictures: every spatial frequency is shown, so every one is identified
    write_rgb8(photos / ("p" + std::to_string(100 + i) + ".png"), at::rand({3, 32, 32}, gen));
  auto r = test::run_flatnet("simulate --images " + q(photos) + " --camera " + q(s.dir / "truth" / "camera.yaml") +
                             " --size 32 --val-fraction 0.25 --seed 3 --out " + q(s.dir / "ds"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  r = test::run_flatnet("simulate --images " + q(photos) + " --camera " + q(s.dir / "other" / "camera.yaml") +
                        " --size 32 --val-fraction 1 --only val --limit 6 --seed 4 --out " + q(s.dir / "other_ds"));
  REQUIRE(r.code == 0);

  // 1. The calibration from the pairs: FlatNet's layout, a camera.yaml with the noise model beside it.
  r = test::run_flatnet("calibrate --dataset " + q(s.dir / "ds") + " --camera " + q(s.dir / "geometry.yaml") +
                        " --out " + q(s.dir / "cal" / "calib.mat") + " --iterations 30");
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("from 72 pairs") && Contains("fit residual"));
  // The tiny rig's masks are random, no moving shadow: the shift structure is tried and rejected.
  CHECK_THAT(r.output, Contains("shift structure rejected"));
  const auto camera = load_camera_config(s.dir / "cal" / "camera.yaml");
  CHECK(camera.knows_noise());
  CHECK(camera.rig.empty());
  CHECK(camera.noise_gain == Approx(1 / 40000.0).epsilon(0.3));
  // The camera fit's threshold covers the pairs' own spread: at least the statistic's own, bounded.
  CHECK(camera.fit_threshold >= 1.0);
  CHECK(camera.fit_threshold < 3.0);
  CHECK_THAT(r.output, Contains("camera fit: its own pairs fit up to the threshold"));
  // Its mask sits square on the sensor: the rotation is searched, and none is written.
  CHECK_THAT(r.output, Contains("rotation: at 0 rad the residual holds"));
  CHECK(std::abs(camera.raw.rotation) < 1e-3);
  const auto estimate = load_calibration(camera.calibration, camera);
  const auto truth_camera = load_camera_config(s.dir / "truth" / "camera.yaml");
  const auto err = calibration_error(estimate, ideal_calibration(load_camera_rig(truth_camera), truth_camera.raw));
  CHECK(err.forward < 0.1);

  // 2. A model for it, trained on its pairs alone (a few steps).
  r = test::run_flatnet("train --config " + q(test::source_dir() / "configs" / "sim_transpose.yaml") + test::kOnDisk +
                        " --set data.dataset=" + q(s.dir / "ds") +
                        " --set data.camera=" + q(s.dir / "cal" / "camera.yaml") +
                        " --set model.unet.width=2 --set model.level_input=false --set train.crop=0"
                        " --set train.iterations=2 --set train.val_every=2 --out " +
                        q(s.dir / "run"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  const auto model = s.dir / "run" / "model.flatnet";

  // 3. Its own camera's captures fit; another camera's do not, and --require-fit refuses them.
  r = test::run_flatnet("infer --model " + q(model) + " --input " + q(s.dir / "ds" / "val_meas.txt") + " --out " +
                        q(s.dir / "rec"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("for camera 'tiny'"));
  auto rows = read_lines(s.dir / "rec" / "camera_fit.csv");
  REQUIRE(rows.size() == 25);
  CHECK(rows[0] == "name,fit,leak,alone,matches");
  for (size_t i = 1; i < rows.size(); ++i) CHECK(rows[i].substr(rows[i].size() - 4) == ",1,1");
  CHECK_THAT(r.output, !Contains("do not fit"));

  r = test::run_flatnet("infer --model " + q(model) + " --input " + q(s.dir / "other_ds" / "val_meas.txt") + " --out " +
                        q(s.dir / "rec_other"));
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("6 of 6 captures do not fit camera 'tiny'") && Contains("calibrate --dataset"));
  rows = read_lines(s.dir / "rec_other" / "camera_fit.csv");
  REQUIRE(rows.size() == 7);
  for (size_t i = 1; i < rows.size(); ++i) CHECK(rows[i].substr(rows[i].size() - 2) == ",0");

  r = test::run_flatnet("infer --require-fit --model " + q(model) + " --input " +
                        q(s.dir / "other_ds" / "val_meas.txt") + " --out " + q(s.dir / "refused"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--require-fit: ") && Contains("do not fit"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "refused"));
}

TEST_CASE("a camera file's fit_threshold and leak_threshold are read, written back and range-checked",
          "[optics][own-camera]") {
  test::Scratch s("fit_threshold");
  const auto base = read_file_text(test::source_dir() / "configs" / "cameras" / "sim.yaml", 1 << 20);
  const auto write = [&](const std::string& extra) {
    std::ofstream(s.dir / "cam.yaml") << base << "\n" << extra;
    return s.dir / "cam.yaml";
  };
  CHECK(load_camera_config(write("")).fit_threshold == 0);  // absent: the statistic's own
  const auto camera = load_camera_config(write("fit_threshold: 1.5\n"));
  CHECK(camera.fit_threshold == 1.5);
  CHECK_THAT(camera_geometry_yaml(camera), Contains("fit_threshold: 1.5"));
  CHECK_THROWS_WITH(load_camera_config(write("fit_threshold: 0.5\n")), Contains("fit_threshold"));
  CHECK_THROWS_WITH(load_camera_config(write("fit_threshold: .nan\n")), Contains("fit_threshold"));

  CHECK(load_camera_config(write("")).leak_threshold == 0);  // absent: noise alone sets it
  const auto leaky = load_camera_config(write("leak_threshold: 2.5\n"));
  CHECK(leaky.leak_threshold == 2.5);
  CHECK_THAT(camera_geometry_yaml(leaky), Contains("leak_threshold: 2.5"));
  CHECK_THROWS_WITH(load_camera_config(write("leak_threshold: 0.9\n")), Contains("leak_threshold"));
  CHECK_THROWS_WITH(load_camera_config(write("leak_threshold: 1e9\n")), Contains("leak_threshold"));
  CHECK_THROWS_WITH(load_camera_config(write("leak_threshold: abc\n")), Contains("cam.yaml"));
}

namespace {

// The shell commands of docs/own-camera.md's walkthrough, as the page writes them: the ```sh blocks of
// its numbered steps ("## 3. ...", not their "###" asides), continuations joined, comments dropped.
std::vector<std::string> walkthrough_commands() {
  const auto lines = read_lines(test::source_dir() / "docs" / "own-camera.md");
  std::vector<std::string> commands;
  bool in_sh = false, in_step = false;
  std::string pending;
  for (const auto& line : lines) {
    if (!in_sh && line.rfind("## ", 0) == 0)
      in_step = line.size() > 3 && std::isdigit(static_cast<unsigned char>(line[3]));
    if (!in_sh && line.rfind("### ", 0) == 0) in_step = false;
    if (line.rfind("```", 0) == 0) {
      in_sh = !in_sh && line == "```sh";
      continue;
    }
    if (!in_sh || !in_step) continue;
    std::string text = line.substr(0, line.find("  #"));
    while (!text.empty() && text.back() == ' ') text.pop_back();
    if (!text.empty() && text.back() == '\\') {
      pending += text.substr(0, text.size() - 1);
      continue;
    }
    text = pending + text;
    pending.clear();
    if (text.rfind("flatnet ", 0) == 0) commands.push_back(text);
  }
  return commands;
}

}  // namespace

TEST_CASE("docs/own-camera.md: the walkthrough's commands run as the page writes them",
          "[cli][own-camera][docs][slow]") {
  const auto commands = walkthrough_commands();
  // Steps 2 (the bench), 3 (calibrate), 4 (adapt) and 5 (infer, eval, report).
  REQUIRE(commands.size() == 6);
  CHECK(commands[0].rfind("flatnet capture-dataset ", 0) == 0);

  // The user's side, at a tiny scale: the geometry (centring level, as the page asks, for the shipped
  // model), and the dataset step 2 would capture, here simulated through a tiny camera's rig.
  test::Scratch s("own_camera_page");
  std::filesystem::create_directories(s.dir / "truth");
  std::filesystem::create_directories(s.dir / "my_cam");
  write_tiny_rig(s.dir / "truth" / "rig.mat", 1);
  write_camera(s.dir / "truth" / "camera.yaml", "rig: rig.mat\n");
  {
    std::ifstream in(test::data_dir() / "cameras" / "tiny.yaml");
    std::string text((std::istreambuf_iterator<char>(in)), {});
    text.replace(text.find("centring: plane"), 15, "centring: level");
    std::ofstream(s.dir / "my_cam" / "geometry.yaml") << text;
  }
  const auto photos = s.dir / "photos";
  std::filesystem::create_directories(photos);
  auto gen = at::detail::createCPUGenerator(9);
  for (int i = 0; i < 48; ++i)
    write_rgb8(photos / ("p" + std::to_string(100 + i) + ".png"), at::rand({3, 32, 32}, gen));
  auto r = test::run_flatnet("simulate --images " + q(photos) + " --camera " + q(s.dir / "truth" / "camera.yaml") +
                             " --size 32 --val-fraction 0.25 --seed 3 --out " + q(s.dir / "my_ds"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  std::filesystem::create_directories(s.dir / "captures");
  for (const char* name : {"p100.png", "p101.png", "p102.png"})
    std::filesystem::copy_file(s.dir / "my_ds" / "meas" / name, s.dir / "captures" / name);
  // The page's paths into the source tree (configs/, models/) resolve from the user's folder.
  for (const char* dir : {"configs", "models"})
    std::filesystem::create_directory_symlink(test::source_dir() / dir, s.dir / dir);

  // The one change to the page's commands: the adaptation's 20 minutes become 5 seconds.
  const std::string budget = "--set train.minutes=20";
  for (size_t i = 1; i < commands.size(); ++i) {
    std::string command = commands[i].substr(std::string("flatnet ").size());
    const auto at = command.find(budget);
    if (command.rfind("train ", 0) == 0) {
      REQUIRE(at != std::string::npos);
      command.replace(at, budget.size(), "--set train.minutes=0.08");
    }
    INFO(commands[i]);
    r = test::run_shell("cd " + q(s.dir) + " && " + FLATNET_BINARY + " " + command);
    INFO(r.output);
    REQUIRE(r.code == 0);
    if (command.rfind("train ", 0) == 0) {
      // The budget alone ends the run, long before the recipe's step count.
      CHECK_THAT(r.output, Contains("data.light: off") && Contains("(train.minutes)"));
      // The recipe's 128-pixel crops on a camera of 32-pixel scenes: whole scenes, said.
      CHECK_THAT(r.output, Contains("train.crop: 0 (whole scenes"));
      CHECK_THAT(r.output, Contains("stopped at the time budget"));
    }
  }
  CHECK(std::filesystem::exists(s.dir / "my_cam" / "camera.yaml"));
  CHECK(std::filesystem::exists(s.dir / "my_run" / "model.flatnet"));
  CHECK(std::filesystem::exists(s.dir / "my_rec" / "p100.png"));
  CHECK(std::filesystem::exists(s.dir / "my_rec" / "camera_fit.csv"));
  CHECK(std::filesystem::exists(s.dir / "my_report"));
}

TEST_CASE(
    "models/stages: the identified camera kept for the calibration-free line loads, and its training copy "
    "differs only in colour_mix and the rig",
    "[own-camera][stages]") {
  const auto dir = test::source_dir() / "models" / "stages" / "identified-camera";
  const auto camera = flatnet::load_camera_config(dir / "camera.yaml");
  const auto train = flatnet::load_camera_config(dir / "camera_train.yaml");
  CHECK(camera.colour_mix.size() == 4);  // identified with the factors: b, gb, gr, r
  CHECK(train.colour_mix.empty());       // the network learns the colour itself
  CHECK(camera.rig.empty());
  REQUIRE(std::filesystem::exists(train.rig));
  CHECK(std::filesystem::equivalent(train.rig, test::rig_path()));
  CHECK(std::filesystem::equivalent(train.calibration, camera.calibration));
  CHECK(train.raw.rotation == camera.raw.rotation);
  CHECK(camera.raw.rotation != 0);  // identified, not the geometry's 0
  CHECK(train.noise_gain == camera.noise_gain);
  CHECK(train.fit_threshold == camera.fit_threshold);
  const auto calib = flatnet::load_calibration(train.calibration, train);
  CHECK(calib.P.sizes() == torch::IntArrayRef({4, 500, 256}));
  CHECK(calib.Q.sizes() == torch::IntArrayRef({4, 620, 256}));
  CHECK(torch::isfinite(calib.P).all().item<bool>());
  CHECK(torch::isfinite(calib.Q).all().item<bool>());
}
