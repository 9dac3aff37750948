// The quality recipe's pieces: real scenes' light (dim, lamps) through the simulator, the
// Tikhonov-regularised pseudo-inverse initialisation, and starting training from a model file.
#include "catch_torch.hpp"

#include <sstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "helpers.hpp"
#include "tiny_model.hpp"
#include "io/image.hpp"
#include "io/camera_config.hpp"
#include "io/raw.hpp"
#include "optics/camera.hpp"
#include "optics/simulator.hpp"
#include "io/config.hpp"
#include "train/data.hpp"
#include "nn/model_file.hpp"
#include "nn/checkpoint.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {
using test::kOnDisk;
using test::q;
}  // namespace

TEST_CASE("scene light: exposure scales linear light, a lamp adds a bright warm disk, the truth clips at white",
          "[quality][light]") {
  const auto display = torch::rand({3, 32, 32});
  SceneLight dim;
  dim.exposure = 0.25;
  CHECK(torch::allclose(lit_scene(display, dim, 0), 0.25 * srgb_to_linear(display), 1e-5, 1e-6));
  SceneLight lamp;
  lamp.lamp = true, lamp.lamp_gain = 30, lamp.lamp_row = 10.5, lamp.lamp_col = 20.5, lamp.lamp_radius = 2;
  const auto lit = lit_scene(display, lamp, 0);
  CHECK(lit[0][10][20].item<double>() > 30);                             // red at the centre: 30 x 1.0 over the scene
  CHECK(lit[2][10][20].item<double>() < lit[0][10][20].item<double>());  // warm: less blue
  CHECK(torch::equal(lit.slice(1, 0, 5), srgb_to_linear(display).slice(1, 0, 5)));  // far rows untouched
  const auto truth = visible_scene(lit, 0);
  CHECK(truth.max().item<double>() == 1.0);
  CHECK(truth[0][10][20].item<double>() == 1.0);
  // Drawing: probability 0 leaves the display's light; 1 always redraws, within the range.
  auto gen = at::detail::createCPUGenerator(4);
  LightAugment none;
  const auto l0 = draw_scene_light(none, 32, gen);
  CHECK((l0.exposure == 1.0 && !l0.lamp));
  LightAugment always;
  always.exposure_probability = 1, always.exposure_min = 0.2, always.exposure_max = 1.5, always.lamp_probability = 1;
  for (int i = 0; i < 20; ++i) {
    const auto l = draw_scene_light(always, 32, gen);
    CHECK((l.exposure >= 0.2 && l.exposure <= 1.5 && l.lamp && l.lamp_gain >= 5 && l.lamp_gain <= 50));
    CHECK((l.lamp_row >= 8 && l.lamp_row <= 24));
  }
}

TEST_CASE("a dim scene's capture is the bright one's scaled, through the real rig", "[quality][light]") {
  const auto rig = load_rig(test::rig_path());
  const auto scene = read_rgb(test::data_dir() / "golden" / "bsds_16052_scene.png");
  SceneLight dim;
  dim.exposure = 0.5;
  const auto bright = simulate_raw(rig, scene, false).to(torch::kFloat64);
  const auto half = simulate_raw_linear(rig, lit_scene(scene, dim, 0), false).to(torch::kFloat64);
  CHECK(torch::equal(simulate_raw_linear(rig, srgb_to_linear(scene), false), simulate_raw(rig, scene, false)));
  // Stored codes = 64 (q); q = round((S + dark) 1023): halving S halves (q - dark code), to within a code.
  const double dark = rig.dark * 1023 * 64;
  CHECK(((half - dark) - 0.5 * (bright - dark)).abs().max().item<double>() <= 64 * 1.01);
}

TEST_CASE("on-the-fly simulation with light augmentation: truth follows the drawn light, deterministic per epoch",
          "[quality][light]") {
  const auto camera = load_camera_config(default_camera_path());
  auto rig = std::make_shared<const Rig>(load_rig(camera.rig));
  std::vector<std::filesystem::path> images{test::data_dir() / "golden" / "bsds_16052_scene.png"};
  LightAugment half;
  half.exposure_probability = 1, half.exposure_min = 0.5, half.exposure_max = 0.5;
  SimulatedPairs dim(images, rig, camera, 0, half), plain(images, rig, camera, 0);
  const auto a = dim.load(0, 0), b = dim.load(0, 0), c = plain.load(0, 0);
  CHECK(torch::equal(a.meas, b.meas));
  CHECK(torch::allclose(a.gt, visible_scene(0.5 * srgb_to_linear(c.gt), 0), 0, 1e-6));
  CHECK(a.gt.mean().item<double>() < 0.85 * c.gt.mean().item<double>());
  CHECK_FALSE(torch::equal(
      a.meas, c.meas));  // (noise-free scaling: the test above; with noise the centred planes are noise-dominated)
  CHECK_FALSE(torch::equal(dim.load(0, 1).meas, a.meas));  // another epoch, another draw of the noise
}

TEST_CASE("a camera's display_gamma shows photographs as v^gamma to simulation and training, and back",
          "[quality][light][display-gamma]") {
  const auto v = torch::linspace(0, 1, 101);
  CHECK(torch::equal(display_to_light(v, 0), srgb_to_linear(v)));
  CHECK(torch::allclose(display_to_light(v, 1.25), torch::pow(v, 1.25)));
  for (const double gamma : {0.0, 0.8, 1.25, 2.2})
    CHECK(torch::allclose(light_to_display(display_to_light(v, gamma), gamma), v, 1e-5, 1e-5));
  CHECK(torch::allclose(light_to_display(torch::tensor({-0.5, 2.0}), 1.25), torch::tensor({0.0, 1.0})));

  // The rig shows a photograph through the camera's curve: simulate_raw of v is simulate_raw_linear
  // of v^gamma, and not of the sRGB curve's light.
  auto camera = load_camera_config(default_camera_path());
  camera.display_gamma = 1.25;
  auto rig = load_camera_rig(camera);
  CHECK(rig.display_gamma == 1.25);
  const auto display = read_rgb(test::data_dir() / "golden" / "bsds_16052_scene.png");
  const auto raw = simulate_raw(rig, display, false);
  CHECK(torch::equal(raw, simulate_raw_linear(rig, torch::pow(display, 1.25), false)));
  CHECK_FALSE(torch::equal(raw, simulate_raw_linear(rig, srgb_to_linear(display), false)));

  // Training: the truth of a dimmed photograph is its light at that exposure through the inverse curve.
  LightAugment half;
  half.exposure_probability = 1, half.exposure_min = 0.5, half.exposure_max = 0.5;
  const auto shared = std::make_shared<const Rig>(rig);
  std::vector<std::filesystem::path> images{test::data_dir() / "golden" / "bsds_16052_scene.png"};
  SimulatedPairs dim(images, shared, camera, 0, half), plain(images, shared, camera, 0);
  const auto a = dim.load(0, 0), c = plain.load(0, 0);
  CHECK(torch::allclose(a.gt, visible_scene(0.5 * torch::pow(c.gt, 1.25), 1.25), 0, 1e-6));
  // 0.5^(1/1.25) = 0.57 of the display's values (the sRGB curve would give about 0.73).
  CHECK(a.gt.mean().item<double>() == Approx(0.574 * c.gt.mean().item<double>()).epsilon(0.02));
}

TEST_CASE("display_gamma in a camera file: read, written, carried, and a power in [0.5, 3]",
          "[quality][display-gamma][io]") {
  const std::string head = "raw_height: 1024\nraw_width: 1280\nscene_size: 256\n";
  CHECK(camera_from_yaml_text(head, "plain.yaml").display_gamma == 0);
  const auto camera = camera_from_yaml_text(head + "display_gamma: 1.25\n", "tone.yaml");
  CHECK(camera.display_gamma == 1.25);
  CHECK(camera_from_yaml_text(camera_geometry_yaml(camera), "model").display_gamma == 1.25);
  for (const char* bad : {"0.3", "45", "-1", ".nan"})
    CHECK_THROWS_WITH(
        camera_from_yaml_text(head + "display_gamma: " + bad + "\n", "bad.yaml"),
        Contains("bad.yaml") && Contains("display_gamma is 0 (the sRGB curve) or a power within [0.5, 3]"));
}

TEST_CASE("judged validation lights item i as display, dim or lamp in turn, the same at every load",
          "[quality][light]") {
  const auto camera = load_camera_config(default_camera_path());
  auto rig = std::make_shared<const Rig>(load_rig(camera.rig));
  const auto image = test::data_dir() / "golden" / "bsds_16052_scene.png";
  const std::vector<std::filesystem::path> images(4, image);
  SimulatedPairs judged(images, rig, camera, 0, LightAugment{}, true), plain(images, rig, camera, 0);
  const auto display = plain.load(0, 0);
  std::vector<Sample> s;
  for (int64_t i = 0; i < 4; ++i) s.push_back(judged.load(i, 0));
  CHECK(s[0].condition == 0);
  CHECK(s[1].condition == 1);
  CHECK(s[2].condition == 2);
  CHECK(s[3].condition == 0);
  CHECK(std::string(kJudgedConditions[s[1].condition]) == "dim");
  // display: the display image is the truth, as in the held-out set.
  CHECK(torch::equal(s[0].gt, display.gt));
  CHECK(torch::equal(s[0].meas, display.meas));
  // dim: a third of the display's light (make_eval_sets.sh's --exposure 0.33).
  CHECK(torch::allclose(s[1].gt, visible_scene(kJudgedDimExposure * srgb_to_linear(display.gt), 0), 0, 1e-6));
  CHECK(s[1].meas.abs().sum().item<double>() < display.meas.abs().sum().item<double>());
  // lamp: a small disk at white in the truth, the rest of the scene as displayed.
  const auto changed = (s[2].gt - display.gt).abs().amax(0) > 1e-6;  // {N,N}
  const auto lamp_pixels = changed.sum().item<int64_t>();
  CHECK(lamp_pixels > 0);
  CHECK(lamp_pixels < 100);
  CHECK(s[2].gt.masked_select(changed.unsqueeze(0).expand_as(s[2].gt)).max().item<double>() == Approx(1.0));
  // Deterministic: a validation set is the same at every validation.
  const auto again = judged.load(2, 0);
  CHECK(torch::equal(again.gt, s[2].gt));
  CHECK(torch::equal(again.meas, s[2].meas));
}

TEST_CASE("train with judged validation: val.csv holds each light's PSNR and picks best.ckpt on their mean",
          "[quality][light][cli][train]") {
  test::Scratch s("judged_validation");
  const auto photos = s.dir / "photos";
  std::filesystem::create_directories(photos);
  for (int copy = 0; copy < 3; ++copy)  // six photographs: three held out, one per light
    for (const char* n : {"bsds_16052_scene.png", "inet_n02980441_castle_scene.png"})
      std::filesystem::copy_file(test::data_dir() / "golden" / n, photos / (std::to_string(copy) + "_" + n));
  const std::string base = "train --config " + q(test::source_dir() / "configs" / "sim_transpose.yaml") +
                           " --set data.camera=" + q(test::source_dir() / "configs" / "cameras" / "sim_level.yaml") +
                           " --set data.images=" + q(photos) +
                           " --set data.val_fraction=0.5 --set model.unet.width=2 --set train.batch=1"
                           " --set train.crop=64 --set train.val_every=2 --set data.val_light=judged";
  // Training captures through a calibration that errs (data.calibration_error), validation not.
  auto r =
      test::run_flatnet(base + " --set data.calibration_error=0.03 --set train.iterations=2 --out " + q(s.dir / "run"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("calibration erring by 3 %") && Contains("validation through the camera's own"));
  const auto lines = read_lines(s.dir / "run" / "val.csv");
  REQUIRE(lines.size() == 2);
  CHECK(lines[0] == "step,psnr,ssim,seconds,psnr_display,psnr_dim,psnr_lamp");
  std::vector<double> fields;
  std::stringstream row(lines[1]);
  for (std::string f; std::getline(row, f, ',');) fields.push_back(std::stod(f));
  REQUIRE(fields.size() == 7);
  CHECK(fields[0] == 2);
  // One held-out photograph per light; the PSNR that picks best.ckpt is their mean.
  CHECK(fields[1] == Approx((fields[4] + fields[5] + fields[6]) / 3).epsilon(1e-4));
  CHECK(checkpoint_best_psnr(s.dir / "run" / "best.ckpt") == Approx(fields[1]).epsilon(1e-4));
  // The same run resumes under the same validation.
  r = test::run_flatnet("train --out " + q(s.dir / "run") + " --resume --set train.iterations=4");
  INFO(r.output);
  CHECK(r.code == 0);
  CHECK(read_lines(s.dir / "run" / "val.csv").size() == 3);
}

TEST_CASE("pinv initialisation: each side's regularised pseudo-inverse of the calibration", "[quality][init]") {
  const auto camera = load_camera_config(default_camera_path());
  auto config = Config::load({}, {"model.inversion.init=pinv", "model.inversion.lambda=1e-8"});
  const auto o = generator_options(config, camera, true);
  const auto calib = load_calibration(camera.calibration, camera);
  const auto W1 = o.inversion.phil.squeeze(2).to(torch::kFloat64), P = calib.P[1];  // gb, as transpose uses
  const auto eye = torch::eye(camera.scene_size, torch::kFloat64);
  CHECK((W1.t().matmul(P) - eye).abs().max().item<double>() < 1e-3);  // W1^T P = I: an inverse on the scene
  config.set("model.inversion.lambda=1e-2");
  const auto W1r = generator_options(config, camera, true).inversion.phil.squeeze(2).to(torch::kFloat64);
  CHECK(W1r.norm().item<double>() < 0.5 * W1.norm().item<double>());  // the weak directions are damped
  config.set("model.inversion.lambda=-1");
  CHECK_THROWS_WITH(generator_options(config, camera, true), Contains("model.inversion.lambda"));
}

TEST_CASE("simulate makes dim, lamp and held-out-only sets, and train --init-from starts from a model",
          "[quality][cli][slow]") {
  test::Scratch s("quality_cli");
  const auto photos = s.dir / "photos";
  std::filesystem::create_directories(photos);
  for (const char* n : {"bsds_16052_scene.png", "inet_n02980441_castle_scene.png",
                        "inet_n02088094_Afghan_hound_scene.png", "imagen_n04356056_1392_sunglasses_scene.png"})
    std::filesystem::copy_file(test::data_dir() / "golden" / n, photos / n);
  auto r = test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "all") +
                             " --val-fraction 0.5 --seed 1");
  REQUIRE(r.code == 0);
  r = test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "dim") +
                        " --val-fraction 0.5 --seed 1 --only val --exposure 0.33");
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("simulated 2 captures"));
  const auto val = read_lines(s.dir / "dim" / "val_meas.txt");
  REQUIRE(val.size() == 2);
  CHECK(read_lines(s.dir / "dim" / "train_meas.txt").empty());
  CHECK(read_lines(s.dir / "all" / "val_meas.txt") == val);  // the same held-out photographs
  const auto name = std::filesystem::path(val[0]).filename();
  CHECK(read_rgb(s.dir / "dim" / "gt" / name).mean().item<double>() <
        0.8 * read_rgb(s.dir / "all" / "gt" / name).mean().item<double>());
  r = test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "lamp") +
                        " --val-fraction 0.5 --seed 1 --only val --lamp");
  REQUIRE(r.code == 0);
  CHECK(read_rgb(s.dir / "lamp" / "gt" / name).max().item<double>() == 1.0);
  auto bad = test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "x") + " --exposure -1");
  CHECK(bad.code == 2);
  CHECK_THAT(bad.output, Contains("--exposure"));
  CHECK_THAT(bad.output, !Contains("simulate.exposure"));  // the library's key, shown to the CLI's user as its flag
  bad = test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "x") + " --only test");
  CHECK(bad.code == 2);
  CHECK_THAT(bad.output, Contains("--only: must be all, train or val"));
  bad =
      test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "x") + " --only val --val-fraction 0");
  CHECK(bad.code == 2);
  CHECK_THAT(bad.output, Contains("selects no images"));

  // --init-from: a fresh run whose step-0 weights are the model's.
  const std::string base = "train --config " + q(test::source_dir() / "configs" / "sim_transpose.yaml") +
                           " --set data.dataset=" + q(s.dir / "all") +
                           " --set model.unet.width=2 --set train.val_every=1" + kOnDisk;
  REQUIRE(test::run_flatnet(base + " --set train.iterations=2 --out " + q(s.dir / "first")).code == 0);
  r = test::run_flatnet(base +
                        " --set train.iterations=1 --set train.lr=0 --set train.lr_discriminator=0 --init-from " +
                        q(s.dir / "first" / "model.flatnet") + " --out " + q(s.dir / "second"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("initialised from"));
  auto weights = [](const std::filesystem::path& model) {
    auto m = load_model_file(model);
    std::map<std::string, torch::Tensor> out;
    for (const auto& p : m.generator->named_parameters()) out[p.key()] = p.value().clone();
    return out;
  };
  const auto a = weights(s.dir / "first" / "model.flatnet"), b = weights(s.dir / "second" / "model.flatnet");
  for (const auto& [k, t] : a) {
    INFO(k);
    CHECK(torch::equal(t, b.at(k)));  // lr 0: the weights are the model's
  }
  // A model whose data-consistency step was set at export: its weights learned without it, and the
  // log says so (it said "was trained with model.consistency.strength 10", issue 113).
  r = test::run_flatnet("export --model " + q(s.dir / "first" / "model.flatnet") + " --data-consistency 10 --out " +
                        q(s.dir / "stepped.flatnet"));
  REQUIRE(r.code == 0);
  r = test::run_flatnet(base +
                        " --set train.iterations=1 --set train.lr=0 --set train.lr_discriminator=0 --init-from " +
                        q(s.dir / "stepped.flatnet") + " --out " + q(s.dir / "from_stepped"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("set at export; its weights were trained without it") && !Contains("was trained with"));
  bad = test::run_flatnet(base + " --set model.unet.width=4 --init-from " + q(s.dir / "first" / "model.flatnet") +
                          " --out " + q(s.dir / "third"));
  CHECK(bad.code == 2);
  CHECK_THAT(bad.output, Contains("model.flatnet") && Contains("the model needs"));
  // A crop not below the scene trains on whole scenes, said in the log (the recipe's crop on a small camera).
  bad = test::run_flatnet(base + " --set train.crop=512 --set train.iterations=1 --out " + q(s.dir / "big"));
  CHECK(bad.code == 0);
  CHECK_THAT(bad.output, Contains("train.crop: 0 (whole scenes: 512 is not below the camera's 256-pixel scene)"));
  bad = test::run_flatnet("train --out " + q(s.dir / "first") + " --resume --init-from " +
                          q(s.dir / "first" / "model.flatnet"));
  CHECK(bad.code == 2);
  CHECK_THAT(bad.output, Contains("cannot be combined with --resume"));
}

// ---- The light level (model.level_input, camera centring "level") ------------------------------

namespace {
using test::tiny_camera;
}  // namespace

TEST_CASE("centring 'level' is plane centring plus each plane's mean, and without_level undoes it",
          "[quality][level]") {
  const auto raw = torch::rand({4, 10, 12}) + torch::arange(4).view({4, 1, 1});
  const auto plane = double_centre(raw, Centring::plane);
  const auto level = double_centre(raw, Centring::level);
  CHECK(torch::allclose(level.mean({1, 2}), raw.mean({1, 2}), 1e-5, 1e-5));
  CHECK(torch::allclose(without_level(level, Centring::level), plane, 1e-5, 1e-5));
  CHECK(torch::equal(without_level(plane, Centring::plane), plane));  // other modes untouched
  // The failure it fixes: a saturated frame and a black one are both flat, and both centre to zeros.
  const auto white = torch::ones({4, 10, 12}), black = torch::zeros({4, 10, 12});
  CHECK(torch::equal(double_centre(white, Centring::plane), double_centre(black, Centring::plane)));
  CHECK_FALSE(torch::equal(double_centre(white, Centring::level), double_centre(black, Centring::level)));
  CHECK(parse_centring("level", "cam.yaml") == Centring::level);
  CHECK_THROWS_WITH(parse_centring("levels", "cam.yaml"), Contains("cam.yaml") && Contains("level"));
}

TEST_CASE("a generator with the light level tells a saturated capture from a black one, and gradients reach it",
          "[quality][level]") {
  const auto level_cam = tiny_camera(Centring::level), plane_cam = tiny_camera(Centring::plane);
  const auto with = Config::load({}, {"model.unet.width=8", "model.level_input=true", "model.bn_momentum=0.1"});
  const auto without = Config::load({}, {"model.unet.width=8", "model.bn_momentum=0.1"});
  torch::manual_seed(0);
  auto g = test::random_generator(with, level_cam);
  {
    torch::NoGradGuard ng;  // weights that read the level strongly
    g->named_parameters()["enhancer.inc.conv.conv.0.weight"].narrow(1, 4, 4).fill_(0.5);
  }
  const auto probe = g->forward(torch::randn({1, 4, 20, 24}));
  REQUIRE(probe.std().item<double>() > 1e-4);  // a live network, not a constant
  auto plain = test::random_generator(without, plane_cam);
  CHECK(g->named_parameters()["enhancer.inc.conv.conv.0.weight"].size(1) == 8);  // 4 first-stage + 4 level channels
  // Two frames with the same pattern, one near black and one near saturation.
  const auto pattern = 0.05 * torch::rand({1, 4, 20, 24});
  const auto bright = pattern + 0.9, dark = pattern;
  CHECK((g->forward(double_centre(bright, Centring::level)) - g->forward(double_centre(dark, Centring::level)))
            .abs()
            .max()
            .item<double>() > 1e-3);
  CHECK(torch::allclose(plain->forward(double_centre(bright, Centring::plane)),
                        plain->forward(double_centre(dark, Centring::plane)), 1e-5, 1e-6));  // blind without it
  // The level never enters the inversion: shifting a plane's DC leaves the first stage unchanged.
  const auto Y = torch::randn({2, 4, 20, 24});
  CHECK(torch::allclose(g->first_stage(Y), g->first_stage(Y + torch::rand({2, 4, 1, 1})), 1e-4, 1e-5));
  // Training: every parameter gets a gradient, on crops too.
  g->train();
  test::check_all_gradients(*g, g->forward(Y + 0.5).mean() + g->forward_crops(Y + 0.5, {{0, 0}, {0, 0}}, 16).mean());
}

TEST_CASE("the model and the camera must agree on the light level, with errors that say how", "[quality][level]") {
  const auto with = Config::load({}, {"model.unet.width=2", "model.level_input=true"});
  const auto without = Config::load({}, {"model.unet.width=2"});
  CHECK_THROWS_WITH(generator_options(with, tiny_camera(Centring::plane), false),
                    Contains("model.level_input") && Contains("centring: level"));
  CHECK_THROWS_WITH(generator_options(without, tiny_camera(Centring::level), false),
                    Contains("centring 'level'") && Contains("centring: plane"));
  const auto o = generator_options(with, tiny_camera(Centring::level), false);
  CHECK_THROWS_WITH(check_camera_for_model(o, tiny_camera(Centring::flatnet)), Contains("'flatnet'"));
}

TEST_CASE("train --init-from a model without the level adds it with zero weights: the same function at step 0",
          "[quality][level]") {
  test::Scratch s("level_init");
  const auto plane_cam = tiny_camera(Centring::plane), level_cam = tiny_camera(Centring::level);
  const auto without = Config::load({}, {"model.unet.width=2", "model.bn_momentum=0.1"});
  const auto with = Config::load({}, {"model.unet.width=2", "model.level_input=true", "model.bn_momentum=0.1"});
  auto old_model = test::random_generator(without, plane_cam);
  save_model_file(s.dir / "old.flatnet", old_model, without, plane_cam);
  Generator g(generator_options(with, level_cam, false));
  init_generator_from(s.dir / "old.flatnet", g);
  g->eval();
  const auto raw = torch::rand({2, 4, 20, 24});
  CHECK(torch::allclose(g->forward(double_centre(raw, Centring::level)),
                        old_model->forward(double_centre(raw, Centring::plane)), 1e-5, 1e-6));
  // The other way (a level model into a plain one) is a shape error naming the tensor.
  auto level_model = test::random_generator(with, level_cam);
  save_model_file(s.dir / "level.flatnet", level_model, with, level_cam);
  Generator plain(generator_options(without, plane_cam, false));
  CHECK_THROWS_WITH(init_generator_from(s.dir / "level.flatnet", plain),
                    Contains("level.flatnet") && Contains("inc.conv.conv.0.weight"));
}

// ---- The measurement pre-processor (model.preprocessor.*) ---------------------------------------

TEST_CASE("a measurement pre-processor: identity when new, positively homogeneous, gradients reach it",
          "[quality][preprocessor]") {
  // Seeded: a width-2 U-Net drawn at random can start with every ReLU of a level dead, and then no
  // gradient reaches anything before it (about one draw in fifteen).
  torch::manual_seed(11);
  PreprocessorOptions o;
  o.width = 3;
  o.depth = 3;
  MeasurementPreprocessor pre(o);
  const auto Y = torch::randn({2, 4, 20, 24});
  CHECK(torch::equal(pre->forward(Y), Y));  // the last convolution starts at zero
  {
    torch::NoGradGuard ng;
    for (auto& p : pre->parameters()) p.uniform_(-0.3, 0.3);
  }
  const auto out = pre->forward(Y);  // {2,4,20,24}
  CHECK(out.sizes() == Y.sizes());
  REQUIRE((out - Y).abs().max().item<double>() > 1e-3);  // a live residual
  // No biases: a brighter exposure of the same capture gives the same output, brighter.
  CHECK(torch::allclose(pre->forward(7.5 * Y), 7.5 * out, 1e-4, 1e-5));
  CHECK(pre->named_parameters().size() == 3);  // three weights, no biases
  // In a generator, on whole captures and on crops: every parameter learns.
  const auto config = Config::load({}, {"model.unet.width=2", "model.preprocessor.width=3", "model.bn_momentum=0.1"});
  auto g = test::random_generator(config, tiny_camera());
  g->train();
  test::check_all_gradients(*g, g->forward(Y).mean() + g->forward_crops(Y, {{0, 0}, {0, 0}}, 16).mean());
  CHECK_THROWS_WITH(Config::load({}, {"model.preprocessor.depth=1"}), Contains("model.preprocessor.depth"));
  CHECK_THROWS_WITH(Config::load({}, {"model.preprocessor.width=-1"}), Contains("model.preprocessor.width"));
  CHECK_THROWS_WITH(Config::load({}, {"model.preprocessor.width=100000"}), Contains("0 (none) to 256 filters"));
}

TEST_CASE("train --init-from a model without a pre-processor adds one as the identity, and a model file keeps it",
          "[quality][preprocessor]") {
  test::Scratch s("preprocessor_init");
  const auto cam = tiny_camera();
  const auto without = Config::load({}, {"model.unet.width=2", "model.bn_momentum=0.1"});
  const auto with = Config::load({}, {"model.unet.width=2", "model.preprocessor.width=4", "model.bn_momentum=0.1"});
  auto old_model = test::random_generator(without, cam);
  save_model_file(s.dir / "old.flatnet", old_model, without, cam);
  Generator g(generator_options(with, cam, false));
  init_generator_from(s.dir / "old.flatnet", g);
  g->eval();
  const auto Y = torch::randn({2, 4, 20, 24});
  CHECK(torch::allclose(g->forward(Y), old_model->forward(Y), 1e-5, 1e-6));  // the same function at step 0
  // Trained, saved and read back: the spec names it, the weights and the output come back.
  auto trained = test::random_generator(with, cam);
  save_model_file(s.dir / "pre.flatnet", trained, with, cam);
  auto m = load_model_file(s.dir / "pre.flatnet");
  CHECK(m.spec.preprocessor_width == 4);
  CHECK(m.spec.preprocessor_depth == 2);
  CHECK(first_stage_text(m.spec).find("measurement pre-processor") != std::string::npos);
  m.generator->eval();
  CHECK(torch::allclose(m.generator->forward(Y), trained->forward(Y), 1e-5, 1e-6));
  CHECK_FALSE(torch::allclose(trained->forward(Y), old_model->forward(Y), 1e-3, 1e-3));
  // The other way, a model with a pre-processor into a config without one: its weights would be
  // lost, so it is refused, naming the setting.
  Generator plain(generator_options(without, cam, false));
  CHECK_THROWS_WITH(init_generator_from(s.dir / "pre.flatnet", plain),
                    Contains("pre.flatnet") && Contains("preprocessor") && Contains("no place"));
}
