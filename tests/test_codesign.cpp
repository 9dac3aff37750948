// Co-design (issue 27, part 2): the differentiable capture, the learned code pair, its files and
// its place in checkpoints.

#include "catch_torch.hpp"

#include "helpers.hpp"
#include "tiny_model.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "io/raw.hpp"
#include "nn/checkpoint.hpp"
#include "nn/model_file.hpp"
#include "optics/camera.hpp"
#include "optics/separable_camera.hpp"
#include "train/codesign.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

std::filesystem::path mls_codes() { return test::source_dir() / "models" / "camera" / "codes_mls.mat"; }

CodesignOptions mls_options() {
  CodesignOptions o;
  o.init_codes = mls_codes();
  o.geometry.centring = Centring::level;
  return o;
}

torch::Tensor random_scenes(int64_t batch, uint64_t seed) {  // {B,3,256,256} linear light
  auto gen = at::detail::createCPUGenerator(seed);
  return at::rand({batch, 3, 256, 256}, gen);
}

}  // namespace

TEST_CASE("the differentiable capture gives the simulator's planes (noise off), for each centring",
          "[codesign][optics]") {
  const auto rig = load_rig(test::rig_path());
  const auto scenes = random_scenes(2, 3);
  for (auto centring : {Centring::plane, Centring::level, Centring::flatnet}) {
    RawGeometry g;
    g.centring = centring;
    auto gen = at::detail::createCPUGenerator(0);
    const auto planes = capture_planes(rig, scenes, g, false, gen);  // {2,4,500,620}
    REQUIRE(planes.sizes() == torch::IntArrayRef({2, 4, 500, 620}));
    for (int64_t b = 0; b < 2; ++b) {
      const auto raw = simulate_raw_linear(rig, scenes[b], false);
      const auto expected = preprocess_raw(raw.to(torch::kFloat32) / 65535.0f, g);
      INFO("centring " << centring_name(centring) << ", scene " << b << ": largest difference "
                       << (planes[b] - expected).abs().max().item<double>());
      CHECK(torch::allclose(planes[b], expected, 0, 2e-5));  // flatnet's mean over the planes sums in another order
    }
  }
  RawGeometry rotated;
  rotated.rotation = 0.01;
  auto gen = at::detail::createCPUGenerator(0);
  CHECK_THROWS_WITH(capture_planes(rig, scenes, rotated, false, gen), Contains("camera.rotation"));
}

TEST_CASE("the capture's noise has the sensor's variance: shot plus read noise, in ADC steps", "[codesign][optics]") {
  const auto rig = load_rig(test::rig_path());
  RawGeometry g;
  g.centring = Centring::none;
  const auto scene = torch::full({1, 3, 256, 256}, 0.1f);  // far from saturation
  auto gen = at::detail::createCPUGenerator(1);
  const auto clean = capture_planes(rig, scene, g, false, gen), noisy = capture_planes(rig, scene, g, true, gen);
  const double step = 64.0 / 65535.0;                    // one 10-bit code in stored units
  const auto signal = clean / step / 1023.0 - rig.dark;  // full-scale units, quantised
  const auto expected_var =
      (signal.clamp_min(0) / rig.full_well + std::pow(rig.read_noise / rig.full_well, 2)) * std::pow(1023.0, 2) +
      1.0 / 12;  // plus the rounding's
  INFO("signal " << signal.min().item<double>() << " .. " << signal.max().item<double>());
  REQUIRE(signal.max().item<double>() < 0.9);
  const double measured = ((noisy - clean) / step).pow(2).mean().item<double>();
  CHECK(measured == Approx(expected_var.mean().item<double>()).epsilon(0.05));
}

TEST_CASE("the learned code pair: gradients reach both codes, binary codes are +-1 with straight-through gradients",
          "[codesign]") {
  for (bool binary : {false, true}) {
    auto o = mls_options();
    o.binary = binary;
    CodePairCamera camera(o);
    const auto [u, v] = camera->codes();
    REQUIRE(u.numel() == 511);
    if (binary)
      CHECK(u.abs().eq(1).all().item<bool>());
    else
      CHECK(u.abs().max().item<double>() <= 0.95 + 1e-6);
    auto gen = at::detail::createCPUGenerator(0);
    const auto planes = camera->capture(random_scenes(1, 4), gen);
    (planes * torch::randn_like(planes)).sum().backward();
    for (const auto& p : camera->named_parameters()) {
      INFO(p.key() << (binary ? " (binary)" : ""));
      REQUIRE(p.value().grad().defined());
      CHECK(torch::isfinite(p.value().grad()).all().item<bool>());
      CHECK(p.value().grad().abs().sum().item<double>() > 0);
    }
  }
}

TEST_CASE("the throughput penalty: zero inside target +- tolerance, growing outside", "[codesign]") {
  auto o = mls_options();
  CodePairCamera camera(o);
  CHECK(camera->throughput().item<double>() == Approx(0.5).margin(1e-3));
  CHECK(camera->throughput_penalty().item<double>() == 0);
  o.target_throughput = 0.3;  // MLS's 0.5 is 0.2 away, 0.15 outside the band
  CodePairCamera far(o);
  CHECK(far->throughput_penalty().item<double>() == Approx(100 * 0.15 * 0.15).epsilon(0.01));
  o.lr = 0;
  CHECK_THROWS_WITH(CodePairCamera(o), Contains("codes.lr"));
  o = mls_options();
  o.init_codes = test::calib_path();  // a .mat without code_rows
  CHECK_THROWS_WITH(CodePairCamera(o), Contains("calib.mat") && Contains("code_rows"));
}

TEST_CASE("a learned camera's files are the camera its codes make, readable by every command", "[codesign][optics]") {
  test::Scratch s("codesign_files");
  CodePairCamera camera(mls_options());
  {
    torch::NoGradGuard no_grad;
    for (auto& p : camera->parameters()) p.add_(0.1 * torch::randn_like(p));
  }
  CameraConfig geometry;
  geometry.raw.centring = Centring::level;
  write_code_camera(s.dir / "cam", camera, geometry);
  const auto cam = load_camera_config(s.dir / "cam" / "camera.yaml");
  CHECK(cam.raw.centring == Centring::level);
  const auto codes = load_code_pair(s.dir / "cam" / "codes.mat");
  const auto [u, v] = camera->codes();
  CHECK(torch::allclose(codes.rows, u.detach().to(torch::kFloat64), 0, 1e-7));
  const auto rig = load_rig(cam.rig);
  const auto expected = separable_rig(codes.rows, codes.cols);
  CHECK(torch::allclose(rig.phil, expected.phil.to(torch::kFloat32), 0, 1e-6));
  const auto calib = load_calibration(cam.calibration, cam);
  const auto ideal = calibration_of(rig, cam.raw.crop, 0.0, 0);  // what `flatnet mask camera` writes, without error
  const double error = ((calib.P - ideal.P).norm() / ideal.P.norm()).item<double>();
  CHECK(error == Approx(0.03).epsilon(0.2));
}

TEST_CASE("checkpoints carry the learned camera and its optimiser, and a mismatched resume is refused",
          "[codesign][train]") {
  test::Scratch s("codesign_ckpt");
  const auto camera_config = test::tiny_camera();
  const auto config = Config::load({}, {"model.unet.width=2"});
  auto g = test::random_generator(config, camera_config);
  Discriminator d(discriminator_options(config));
  torch::optim::Adam opt_g(g->parameters()), opt_d(d->parameters());
  CodePairCamera camera(mls_options());
  torch::optim::Adam opt_c(camera->parameters(), torch::optim::AdamOptions(0.01));
  auto gen = at::detail::createCPUGenerator(0);
  camera->capture(random_scenes(1, 5), gen).pow(2).mean().backward();
  opt_c.step();  // moments to save
  TrainState state;
  state.rng_state = at::detail::getDefaultCPUGenerator().get_state();
  const auto identity = model_identity(config, camera_config);
  save_checkpoint(s.dir / "with.ckpt", g, d, opt_g, opt_d, state, identity, nullptr, {camera.get(), &opt_c});
  save_checkpoint(s.dir / "without.ckpt", g, d, opt_g, opt_d, state, identity);

  CodePairCamera restored(mls_options());
  torch::optim::Adam opt_r(restored->parameters(), torch::optim::AdamOptions(0.01));
  load_checkpoint(s.dir / "with.ckpt", g, d, opt_g, opt_d, nullptr, {restored.get(), &opt_r});
  CHECK(torch::equal(restored->codes().first, camera->codes().first));
  CHECK(torch::equal(restored->codes().second, camera->codes().second));
  CHECK(opt_r.state().size() == 2);
  CHECK_THROWS_WITH(load_checkpoint(s.dir / "with.ckpt", g, d, opt_g, opt_d),
                    Contains("with.ckpt") && Contains("holds a learned camera"));
  CHECK_THROWS_WITH(load_checkpoint(s.dir / "without.ckpt", g, d, opt_g, opt_d, nullptr, {restored.get(), &opt_r}),
                    Contains("without.ckpt") && Contains("holds no learned camera"));
}

TEST_CASE("flatnet train with codes.learn: the codes move, the camera is written, the run resumes",
          "[codesign][cli][train]") {
  test::Scratch s("codesign_cli");
  const auto photos = test::make_photos(s.dir / "photos");
  const auto q = [](const std::filesystem::path& p) { return "'" + p.string() + "'"; };
  const std::string base = "train --config " + q(test::source_dir() / "configs" / "sim_transpose.yaml") +
                           " --set data.camera=" + q(test::source_dir() / "configs" / "cameras" / "sim_level.yaml") +
                           " --set data.images=" + q(photos) +
                           " --set data.val_fraction=0.5 --set model.unet.width=2 --set train.batch=1"
                           " --set train.crop=64 --set codes.learn=true --set codes.lr=0.1 --set codes.freeze_at=0.5"
                           " --set train.val_every=2 --set train.log_every=1";
  auto r = test::run_flatnet(base + " --set train.iterations=2 --out " + q(s.dir / "run"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("co-design: codes from mls"));
  for (const char* f : {"codes.mat", "rig.mat", "calib.mat", "camera.yaml"})
    CHECK(std::filesystem::exists(s.dir / "run" / "camera" / f));
  const auto start = load_code_pair(mls_codes()), learned = load_code_pair(s.dir / "run" / "camera" / "codes.mat");
  CHECK_FALSE(torch::allclose(start.rows.clamp(-0.95, 0.95), learned.rows, 0, 1e-4));  // the codes learned
  // Resumed: the codes come back from the checkpoint and, past codes.freeze_at, stay as they are.
  r = test::run_flatnet("train --out " + q(s.dir / "run") + " --resume --set train.iterations=4");
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("resumed at step 2"));
  const auto after = load_code_pair(s.dir / "run" / "camera" / "codes.mat");
  CHECK(torch::equal(after.rows, learned.rows));
  // The written camera is a camera: Tikhonov reconstructs with it.
  CHECK(load_camera_config(s.dir / "run" / "camera" / "camera.yaml").raw.centring == Centring::level);
  // Co-design simulates its captures: a dataset on disk is refused before anything is written.
  r = test::run_flatnet(base + test::kOnDisk + " --set train.iterations=1 --out " + q(s.dir / "disk"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("codes.learn") && Contains("data.source: simulate"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "disk"));
  // The codes it learns are their own calibration: an erring one to train through is refused.
  r = test::run_flatnet(base + " --set data.calibration_error=0.1 --set train.iterations=1 --out " + q(s.dir / "err"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("data.calibration_error") && Contains("codes.learn"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "err"));
}
