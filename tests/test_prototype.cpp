// FlatNet's real prototype as a camera flatnet knows: its calibration recovered from captures and
// FlatNet's own reconstructions of them (`calibrate --references`), a held-out capture reconstructed
// with it by `recon`, and the compact calibration file (profiles and shifts) that carries it.
#include "catch_torch.hpp"

#include "core/error.hpp"
#include "helpers.hpp"
#include "io/camera_config.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "optics/calibrate_references.hpp"
#include "optics/camera.hpp"
#include "optics/shift_structure.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;
using test::q;
using test::write_file;

TEST_CASE(
    "a compact calibration (profiles and shifts) expands to the factors it was made from, and a lying one is named",
    "[optics][calibrate][safe]") {
  test::Scratch s("compact_calibration");
  CameraConfig camera;
  camera.raw.crop = {0, 0, 40, 50};
  camera.scene_size = 16;
  auto gen = at::detail::createCPUGenerator(5);
  const double shift_rows = -0.47, shift_cols = 1.3;
  const auto fr = at::randn({4, 40 + 7 + 1}, gen).to(torch::kFloat64);   // m + floor(0.47 * 15) + 1
  const auto fc = at::randn({4, 50 + 19 + 1}, gen).to(torch::kFloat64);  // n + floor(1.3 * 15) + 1
  save_shift_calibration(s.dir / "c.mat", fr, fc, shift_rows, shift_cols);
  const auto calib = load_calibration(s.dir / "c.mat", camera);
  CHECK(calib.P.sizes() == torch::IntArrayRef({4, 40, 16}));
  CHECK(calib.Q.sizes() == torch::IntArrayRef({4, 50, 16}));
  CHECK(torch::allclose(calib.P, shift_factor(fr, 40, 16, shift_rows, 1.0)));
  CHECK(torch::allclose(calib.Q, shift_factor(fc, 50, 16, shift_cols, 1.0)));
  // Lies: a short profile, a shift that is not a number or absurd, a profile of another camera.
  save_shift_calibration(s.dir / "short.mat", fr.narrow(1, 0, 20), fc, shift_rows, shift_cols);
  CHECK_THROWS_WITH(load_calibration(s.dir / "short.mat", camera), Contains("short.mat") && Contains("profile_rows"));
  save_shift_calibration(s.dir / "nan.mat", fr, fc, NAN, shift_cols);
  CHECK_THROWS_WITH(load_calibration(s.dir / "nan.mat", camera), Contains("nan.mat") && Contains("shift_rows"));
  save_shift_calibration(s.dir / "huge.mat", fr, fc, shift_rows, 1e9);
  CHECK_THROWS_WITH(load_calibration(s.dir / "huge.mat", camera), Contains("huge.mat") && Contains("shift"));
  auto bad = fr.clone();
  bad[0][3] = INFINITY;
  save_shift_calibration(s.dir / "inf.mat", bad, fc, shift_rows, shift_cols);
  CHECK_THROWS_WITH(load_calibration(s.dir / "inf.mat", camera), Contains("inf.mat") && Contains("NaN or Inf"));
}

TEST_CASE(
    "FlatNet's prototype: a calibration from three captures and FlatNet's reconstructions reconstructs the fourth",
    "[cli][calibrate][flatnet-data][slow]") {
  const auto data = test::shared_dir() / "data" / "flatnet";
  if (!std::filesystem::exists(data / "fc_9.png") || !std::filesystem::exists(data / "rec_9.png"))
    SKIP_TEST("no ../shared/data/flatnet captures and reconstructions");
  test::Scratch s("prototype_calibration");
  write_file(s.dir / "captures.txt", "fc_6.png\nfc_7.png\nfc_8.png\n");
  write_file(s.dir / "references.txt", "rec_6.png\nrec_7.png\nrec_8.png\n");
  const auto camera = test::source_dir() / "configs" / "cameras" / "flatnet_prototype_level.yaml";
  auto r = test::run_flatnet("calibrate --references --meas-list " + q(s.dir / "captures.txt") + " --gt-list " +
                             q(s.dir / "references.txt") + " --root " + q(data) + " --camera " + q(camera) + " --out " +
                             q(s.dir / "cal" / "calib.mat") +
                             " --compact --min-shift 0.3 --max-shift 1"  // a narrower search than the default, for time
                             " --scene-light 0");  // in FlatNet's references' units, as the shipped camera is
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("leave-one-out") && Contains("fc_7.png") && Contains("shift structure"));
  CHECK_THAT(r.output, Contains("the calibration is in the references' units"));
  // The shadow's move, as the study found it: about -0.47 sensor pixels per scene pixel on both axes.
  const auto yaml = test::read_file(s.dir / "cal" / "camera.yaml");
  CHECK_THAT(yaml, Contains("-0.47"));
  // The calibration's own uncertainty (the leave-one-out jackknife), with what trains with it.
  CHECK_THAT(yaml, Contains("coded light is uncertain by") && Contains("data.calibration_error"));
  CHECK_THAT(r.output, Contains("from the whole calibration (P, Q, coded light)"));
  // The sensor's noise model, the camera fit's thresholds and the open light, from the captures.
  CHECK_THAT(yaml, Contains("noise_gain:") && Contains("fit_threshold:") && Contains("open_light:"));
  const auto written = load_camera_config(s.dir / "cal" / "camera.yaml");
  CHECK(written.noise_gain > 1e-5);
  CHECK(written.noise_gain < 1e-4);
  CHECK(written.open_light > 2);
  CHECK(written.open_light < 6);
  CHECK(std::filesystem::file_size(s.dir / "cal" / "calib.mat") < 100000);  // profiles, not matrices
  std::filesystem::create_directories(s.dir / "in");
  std::filesystem::copy_file(data / "fc_9.png", s.dir / "in" / "fc_9.png");
  // The held-out capture fits the camera the other three identified (--require-fit).
  r = test::run_flatnet("recon --method tikhonov --camera " + q(s.dir / "cal" / "camera.yaml") + " --input " +
                        q(s.dir / "in") + " --out " + q(s.dir / "rec") + " --require-fit");
  INFO(r.output);
  REQUIRE(r.code == 0);
  // recon writes sRGB; FlatNet's reconstruction is linear: compare in linear light, per Bayer channel,
  // leaving out FlatNet's pixels clipped at zero.
  const auto ours = rgb_to_bayer_planes(srgb_to_linear(read_rgb(s.dir / "rec" / "fc_9.png")));
  const auto theirs = rgb_to_bayer_planes(read_rgb(data / "rec_9.png"));
  const auto correlation = reference_correlation(ours, theirs);
  for (const double c : correlation) CHECK(c > 0.9);
}
