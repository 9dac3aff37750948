// Hostile inputs, fifth round (issue 92): the few-captures calibration (an output on a reference, a
// pair listed twice, an unbounded shift search, a rotation search that cannot run), compact
// calibrations (full matrices beside them, a profile one sample short, a scale of 1e300), camera
// files (colour-mix rows that do not sum to 1, the most hot pixels flatnet writes, a tiny noise gain),
// and a bench where none belongs (co-design, a model file). Each case failed before its fix.
#include "catch_torch.hpp"

#include <cmath>

#include "core/error.hpp"
#include "helpers.hpp"
#include "io/camera_config.hpp"
#include "io/config.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "io/safetensors.hpp"
#include "nn/model_file.hpp"
#include "optics/camera.hpp"
#include "optics/shift_structure.hpp"
#include "tiny_model.hpp"
#include "train/experiment.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;
using test::q;
using test::read_file;
using test::write_file;

namespace {

// Three capture / reference pairs for the tiny camera (tests/data/cameras/tiny.yaml: 128x160 raw
// frames, 32-pixel scenes) in `dir`, with the lists `captures.txt` and `references.txt` naming
// `captures` and `references` (file names in `dir`).
std::string reference_lists(const std::filesystem::path& dir, const std::vector<std::string>& captures,
                            const std::vector<std::string>& references) {
  auto gen = at::detail::createCPUGenerator(5);
  for (int i = 1; i <= 3; ++i) {
    write_gray16(dir / ("c" + std::to_string(i) + ".png"), (at::rand({128, 160}, gen) * 900 + 60).to(torch::kInt32));
    write_rgb8(dir / ("r" + std::to_string(i) + ".png"), at::rand({3, 32, 32}, gen));
  }
  std::string c, r;
  for (const auto& name : captures) c += name + "\n";
  for (const auto& name : references) r += name + "\n";
  write_file(dir / "captures.txt", c);
  write_file(dir / "references.txt", r);
  return "calibrate --references --meas-list " + q(dir / "captures.txt") + " --gt-list " + q(dir / "references.txt") +
         " --camera " + q(test::data_dir() / "cameras" / "tiny.yaml");
}

}  // namespace

TEST_CASE("calibrate --references never writes over one of the files it reads, even with --force",
          "[safe][hostile][calibrate]") {
  test::Scratch s("round5_reference_out");
  const auto base = reference_lists(s.dir, {"c1.png", "c2.png", "c3.png"}, {"r1.png", "r2.mat", "r3.png"});
  write_file(s.dir / "r2.mat", "a reference the user keeps");  // its content is never read before the check
  {
    const auto r = test::run_flatnet(base + " --out " + q(s.dir / "r2.mat") + " --force");
    CHECK(r.code == 2);
    CHECK_THAT(r.output, Contains("r2.mat") && Contains("is also the input"));
  }
  CHECK(read_file(s.dir / "r2.mat") == "a reference the user keeps");
  // The camera.yaml written beside the calibration is checked the same way: a reference named camera.yaml.
  write_file(s.dir / "camera.yaml", "name: a reference named camera.yaml\n");
  const auto beside = reference_lists(s.dir, {"c1.png", "c2.png", "c3.png"}, {"r1.png", "camera.yaml", "r3.png"});
  const auto r = test::run_flatnet(beside + " --out " + q(s.dir / "calib.mat") + " --force");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("camera.yaml") && Contains("is also the input"));
  CHECK(read_file(s.dir / "camera.yaml") == "name: a reference named camera.yaml\n");
}

TEST_CASE("calibrate --references names a pair listed twice, by file or by pixels, before any fit",
          "[safe][hostile][calibrate]") {
  test::Scratch s("round5_reference_repeats");
  auto r = test::run_flatnet(reference_lists(s.dir, {"c1.png", "c2.png", "c1.png"}, {"r1.png", "r2.png", "r1.png"}) +
                             " --out " + q(s.dir / "out" / "calib.mat"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("c1.png") && Contains("repeats pair 1") && Contains("the same file"));
  // The same capture under another name.
  std::filesystem::copy_file(s.dir / "c2.png", s.dir / "c2_copy.png");
  std::filesystem::copy_file(s.dir / "r2.png", s.dir / "r2_copy.png");
  r = test::run_flatnet(
      reference_lists(s.dir, {"c1.png", "c2.png", "c2_copy.png"}, {"r1.png", "r2.png", "r2_copy.png"}) + " --out " +
      q(s.dir / "out" / "calib.mat"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("c2_copy.png") && Contains("repeats pair 2") && Contains("the same pixels"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "out" / "calib.mat"));
}

TEST_CASE("the shift search's range is bounded, and a rotation search that cannot run is refused",
          "[safe][hostile][calibrate]") {
  test::Scratch s("round5_shift_range");
  const auto base = reference_lists(s.dir, {"c1.png", "c2.png", "c3.png"}, {"r1.png", "r2.png", "r3.png"});
  for (const std::string range : {"--min-shift 1e-300", "--min-shift 0.01", "--max-shift 1e9", "--min-shift nan"}) {
    INFO(range);
    const auto r = test::run_flatnet(base + " " + range + " --out " + q(s.dir / "calib.mat"));
    CHECK(r.code == 2);
    CHECK_THAT(r.output, Contains("--min-shift") || Contains("--max-shift"));
  }
  // The library bounds the grid too, whoever calls it.
  ShiftFitOptions o;
  o.min_shift = 1e-300;
  const auto G = torch::eye(8, torch::kFloat64).unsqueeze(0), H = torch::zeros({1, 8, 8}, torch::kFloat64);
  CHECK_THROWS_WITH(search_shift(G, H, o, 0.0), Contains("0.05"));
  o.min_shift = 0.5, o.grid_step = 1e-12;
  CHECK_THROWS_WITH(search_shift(G, H, o, 0.0), Contains("grid step"));
  // --structure free fits no angle: --rotation estimate with it is refused, not ignored.
  std::filesystem::create_directories(s.dir / "ds");
  write_file(s.dir / "ds" / "train_meas.txt", "../c1.png\n../c2.png\n");
  write_file(s.dir / "ds" / "train_gt.txt", "../r1.png\n../r2.png\n");
  const auto r = test::run_flatnet("calibrate --dataset " + q(s.dir / "ds") + " --camera " +
                                   q(test::data_dir() / "cameras" / "tiny.yaml") + " --out " + q(s.dir / "f.mat") +
                                   " --structure free --rotation estimate");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--rotation") && Contains("--structure shift"));
}

TEST_CASE("a compact calibration names its file and variable, and never hides full matrices or a wild scale",
          "[safe][hostile][calibration]") {
  test::Scratch s("round5_compact");
  CameraConfig camera;
  camera.raw.raw_height = 128, camera.raw.raw_width = 160;
  camera.raw.crop = {0, 0, 40, 50};
  camera.scene_size = 16;
  const double shift_rows = -0.6, shift_cols = 1.3;
  const auto L_rows = shift_profile_length(40, 16, shift_rows, 1.0),
             L_cols = shift_profile_length(50, 16, shift_cols, 1.0);
  auto gen = at::detail::createCPUGenerator(4);
  const auto fr = at::rand({4, L_rows}, gen).to(torch::kFloat64), fc = at::rand({4, L_cols}, gen).to(torch::kFloat64);
  save_shift_calibration(s.dir / "ok.mat", fr, fc, shift_rows, shift_cols);
  CHECK_NOTHROW(load_calibration(s.dir / "ok.mat", camera));
  // One sample short of what the shift needs: the file and the variable named, not "a shift profile".
  save_shift_calibration(s.dir / "short.mat", fr.narrow(1, 0, L_rows - 1), fc, shift_rows, shift_cols);
  CHECK_THROWS_WITH(load_calibration(s.dir / "short.mat", camera), Contains("short.mat") && Contains("profile_rows"));
  // Scaled by 1e300 (and by 1e-300): refused, named, instead of uniform black pictures.
  save_shift_calibration(s.dir / "huge.mat", fr * 1e300, fc, shift_rows, shift_cols);
  CHECK_THROWS_WITH(load_calibration(s.dir / "huge.mat", camera), Contains("huge.mat") && Contains("largest entry"));
  const auto full = load_calibration(s.dir / "ok.mat", camera);
  save_calibration(s.dir / "full_huge.mat", {full.P * 1e300, full.Q});
  CHECK_THROWS_WITH(load_calibration(s.dir / "full_huge.mat", camera),
                    Contains("full_huge.mat") && Contains("largest entry"));
  save_calibration(s.dir / "full_tiny.mat", {full.P, full.Q * 1e-300});
  CHECK_THROWS_WITH(load_calibration(s.dir / "full_tiny.mat", camera), Contains("full_tiny.mat") && Contains("Q"));
  // A compact file that also holds full matrices: which one was meant is asked, not guessed.
  write_mat(s.dir / "both.mat", {{"profile_rows", fr},
                                 {"profile_cols", fc},
                                 {"shift_rows", torch::tensor(shift_rows, torch::kFloat64)},
                                 {"shift_cols", torch::tensor(shift_cols, torch::kFloat64)},
                                 {"P1b", full.P[0]}});
  CHECK_THROWS_WITH(load_calibration(s.dir / "both.mat", camera), Contains("both.mat") && Contains("full matrices"));
}

TEST_CASE("camera files: colour-mix rows sum to 1, and the most hot pixels flatnet writes read back",
          "[safe][hostile][yaml]") {
  const std::string head = "name: c\nraw_height: 1024\nraw_width: 1280\ncrop: [0, 0, 500, 620]\n";
  CHECK_NOTHROW(
      camera_from_yaml_text(head + "colour_mix: [[0, 0, 1], [0, 1, 0], [0, 1, 0], [0.98, 0.01, 0.01]]\n", "ok.yaml"));
  CHECK_THROWS_WITH(
      camera_from_yaml_text(head + "colour_mix: [[0, 0, 2], [0, 1, 0], [0, 1, 0], [1, 0, 0]]\n", "double.yaml"),
      Contains("double.yaml") && Contains("row 1 (b) sums to 2") && Contains("sum to 1"));
  // kMaxHotPixels pixels, written by the camera writer: read back whole (the YAML reader's node bound
  // allows the largest file flatnet writes).
  CameraConfig c = camera_from_yaml_text(head, "head.yaml");
  for (int64_t i = 0; i < kMaxHotPixels; ++i) c.raw.hot_pixels.push_back({1023 - i % 1024, 1279 - i / 1024});
  const auto back = camera_from_yaml_text(camera_geometry_yaml(c), "many.yaml");
  CHECK((back.raw.hot_pixels == c.raw.hot_pixels));
  c.raw.hot_pixels.push_back({1000, 0});
  CHECK_THROWS_WITH(camera_from_yaml_text(camera_geometry_yaml(c), "more.yaml"),
                    Contains("more.yaml") && Contains("at most 100000"));
}

TEST_CASE("a sensor whose full well is beyond float32's counts reads the signal, not code 0",
          "[safe][hostile][optics]") {
  Rig rig;
  rig.adc_bits = 10;
  rig.dark = 0.02;
  const auto signal = torch::full({1, 4, 8, 8}, 0.5);
  for (const double full_well : {4e4, 1e13, 1e300, static_cast<double>(INFINITY)}) {
    INFO(full_well);
    rig.full_well = full_well;
    rig.read_noise = std::isfinite(full_well) ? 1e-3 * full_well : 0.0;
    auto gen = at::detail::createCPUGenerator(1);
    const auto codes = sensor_readout(rig, signal, true, gen).to(torch::kFloat64);
    CHECK(codes.mean().item<double>() == Approx(0.52 * 1023).margin(3));
  }
}

TEST_CASE("a bench belongs to a simulated camera alone: co-design and model files refuse one",
          "[safe][hostile][model]") {
  test::Scratch s("round5_bench");
  auto camera = test::tiny_camera();
  camera.name = "tiny";
  const auto config = Config::load({}, {"model.unet.width=2", "model.inversion.init=random"});
  Generator g(generator_options(config, camera, false));
  save_model_file(s.dir / "m.flatnet", g, config, camera);
  auto file = read_safetensors(s.dir / "m.flatnet");
  file.metadata.at("camera") += "bench: {crosstalk: 0.2}\n";
  write_safetensors(s.dir / "bench.flatnet", file.tensors, file.metadata);
  CHECK_NOTHROW(load_model_file(s.dir / "m.flatnet"));
  CHECK_THROWS_WITH(load_model_file(s.dir / "bench.flatnet"), Contains("bench.flatnet") && Contains("bench:"));
  // Co-design simulates its learned codes on an ideal bench: a camera with a bench is refused.
  auto bench_camera = load_camera_config(default_camera_path());
  const auto codesign = Config::load({}, {"codes.learn=true", "codes.init=mls", "data.source=simulate"});
  CHECK_NOTHROW(codesign_options(codesign, bench_camera));
  bench_camera.bench.crosstalk = 0.2;
  CHECK_THROWS_WITH(codesign_options(codesign, bench_camera), Contains("bench"));
}

TEST_CASE("calibrate --references names a white capture that is saturated, foreign or missing before any fit",
          "[safe][hostile][calibrate]") {
  test::Scratch s("round5_white_capture");
  const auto lists = reference_lists(s.dir, {"c1.png", "c2.png", "c3.png"}, {"r1.png", "r2.png", "r3.png"});
  const auto base = lists + " --out " + q(s.dir / "out" / "calib.mat");
  write_gray16(s.dir / "white_sat.png", torch::full({128, 160}, 1023 * 64, torch::kInt32));
  write_gray16(s.dir / "white_small.png", torch::full({64, 80}, 500 * 64, torch::kInt32));
  const std::vector<std::pair<std::string, std::vector<std::string>>> cases = {
      {"--white-capture " + q(s.dir / "white_sat.png"), {"white_sat.png", "saturated", "--white-light"}},
      {"--white-capture " + q(s.dir / "white_small.png"), {"white_small.png"}},
      {"--white-capture " + q(s.dir / "no_white.png"), {"no_white.png"}},
      {"--white-capture " + q(s.dir / "white_sat.png") + " --white-light 0", {"--white-light", "(0, 1000]"}},
      {"--white-capture " + q(s.dir / "white_sat.png") + " --white-light nan", {"--white-light"}},
      // The scenes' prior is the unit without a white capture: with one, or absurd, it is refused at once.
      {"--white-capture " + q(s.dir / "white_sat.png") + " --scene-light 0.1", {"--scene-light", "--white-capture"}},
      {"--scene-light -1", {"--scene-light", "1000"}},
      {"--scene-light inf", {"--scene-light"}},
  };
  for (const auto& [flags, words] : cases) {
    INFO(flags);
    const auto r = test::run_flatnet(base + " " + flags);
    CHECK(r.code == 2);
    for (const auto& w : words) CHECK_THAT(r.output, Contains(w));
    CHECK_THAT(r.output, !Contains("leave-one-out"));  // named before the calibration's minutes
  }
  // The white capture is an input: no output lands on it, even with --force; and it belongs to --references.
  write_gray16(s.dir / "white_frame.png", torch::full({128, 160}, 500 * 64, torch::kInt32));
  std::filesystem::rename(s.dir / "white_frame.png", s.dir / "white.mat");  // a .mat name, as --out needs
  auto r = test::run_flatnet(lists + " --white-capture " + q(s.dir / "white.mat") + " --out " + q(s.dir / "white.mat") +
                             " --force");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("white.mat") && Contains("is also the input"));
  r = test::run_flatnet("calibrate --dataset " + q(s.dir) + " --camera " +
                        q(test::data_dir() / "cameras" / "tiny.yaml") + " --white-capture " + q(s.dir / "white.mat") +
                        " --out " + q(s.dir / "out" / "calib.mat"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--white-capture") && Contains("--references"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "out" / "calib.mat"));
}
