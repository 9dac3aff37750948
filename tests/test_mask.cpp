// Mask design: baselines, the capture/Wiener pipeline's physics, the throughput rule, gradients,
// and the mask commands' errors.
#include "catch_torch.hpp"
#include <fstream>
#include <map>
#include <regex>
#include <sstream>
#include <set>
#include <stdexcept>

#include "core/error.hpp"
#include "core/util.hpp"
#include "eval/mask_report.hpp"
#include "eval/metrics.hpp"
#include "helpers.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "nn/model_file.hpp"
#include "io/safetensors.hpp"
#include "optics/simulator.hpp"
#include "eval/mask_score.hpp"
#include "train/mask_trainer.hpp"
#include "train/options.hpp"
#include "train/separable_trainer.hpp"
#include "train/trainer_checkpoint.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {
using test::q;
torch::Tensor smooth_scenes(int64_t b) {  // {b,256,256} in [0,1], low-pass random
  auto x = torch::rand({b, 1, 32, 32});
  return torch::upsample_bilinear2d(x, {256, 256}, false).squeeze(1);
}
}  // namespace

TEST_CASE("baseline masks: MLS passes half the light, the 02 mask about 2%", "[mask]") {
  WienerCamera cam;
  const auto mls = load_mask_window("mls", cam);
  REQUIRE(mls.sizes() == torch::IntArrayRef({500, 620}));
  CHECK(throughput(mls) == Approx(0.5).margin(0.01));
  const auto m02 = load_mask_window("m02", cam);
  CHECK(throughput(m02) == Approx(21.0 * 21.0 * 16.0 / (500.0 * 620.0)).epsilon(1e-6));  // 21 open of 31, squared
  CHECK(((mls == 0) | (mls == 1)).all().item<bool>());
}

TEST_CASE("capture is a convolution with unit DC gain and Wiener inverts it", "[mask]") {
  WienerCamera cam;
  cam.noise_sigma = 0;
  const auto P = psf_spectrum(load_mask_window("mls", cam));
  // Unit DC gain for a half-open mask: P(0) = 2 * throughput.
  CHECK(P[0][0].abs().item<double>() == Approx(2 * throughput(load_mask_window("mls", cam))).epsilon(1e-4));
  const auto x = smooth_scenes(2);
  const auto y = capture(x, P, cam);
  REQUIRE(y.sizes() == torch::IntArrayRef({2, 500, 620}));
  const auto rec = wiener(y, P, torch::tensor(1e-9), cam);
  const auto mse = (rec - x).pow(2).mean().item<double>();
  CHECK(-10 * std::log10(mse) > 40);  // noise-free and well conditioned: near exact
  // Adjoint identity: with a huge gamma, Wiener is the adjoint A^T / gamma: <A x, y> = <x, A^T y>.
  const auto r = torch::randn({2, 500, 620});
  const double gamma = 1e6;
  const double lhs = (capture(x, P, cam) * r).sum().item<double>();
  const double rhs = gamma * (x * wiener(r, P, torch::tensor(gamma), cam)).sum().item<double>();
  CHECK(lhs == Approx(rhs).epsilon(1e-3));
}

TEST_CASE("learnable mask: throughput rule, exact constraint gradient, binarisation, errors", "[mask]") {
  for (const auto projection : {MaskProjection::sigmoid, MaskProjection::clamp}) {
    MaskOptions o;
    o.rank = 3;
    o.projection = projection;
    MaskModel m(o);
    const auto w = m->window();
    CHECK(w.sizes() == torch::IntArrayRef({500, 620}));
    CHECK(throughput(w) == Approx(0.5).margin(1e-3));
    CHECK(w.min().item<double>() >= 0);
    CHECK(w.max().item<double>() <= 1);
    // The mean is held fixed, so its gradient with respect to the parameters vanishes...
    w.mean().backward();
    CHECK(m->U.grad().abs().max().item<double>() < 1e-6);
    // ...while other functions of the mask still get gradients.
    m->zero_grad();
    m->window().pow(2).sum().backward();
    CHECK(m->U.grad().abs().max().item<double>() > 0);
  }
  MaskOptions cap;
  cap.throughput = ThroughputRule::cap;
  cap.target = 0.9;  // a random sigmoid mask passes ~0.5 < 0.9: left alone
  CHECK(throughput(MaskModel(cap)->window()) < 0.6);
  MaskOptions bin;
  bin.binary = true;
  const auto wb = MaskModel(bin)->window();
  CHECK(((wb == 0) | (wb == 1)).all().item<bool>());
  CHECK(throughput(wb) == Approx(0.5).margin(0.01));
  MaskOptions bad;
  bad.rank = 0;
  CHECK_THROWS_WITH(MaskModel(bad), Contains("mask.rank"));
  CHECK_THROWS_WITH(parse_mask_projection("tanh"), Contains("mask.projection") && Contains("tanh"));
  CHECK_THROWS_WITH(parse_throughput_rule("half"), Contains("mask.throughput"));
  CHECK_THROWS_WITH(parse_mask_init("lena"), Contains("mask.init"));
  CHECK(parse_throughput_rule("free") == ThroughputRule::free);
}

TEST_CASE("mask training: gradients reach U, V and gamma, and the outputs are written", "[mask][slow]") {
  test::Scratch s("masktrain");
  MaskOptions o;
  o.rank = 2;
  MaskModel m(o);
  const auto before = m->U.clone();
  WienerCamera cam;
  MaskTrainOptions t;
  t.iterations = 3, t.batch = 2, t.optimizer = "adam", t.lr = 1e-2, t.val_every = 3, t.log_every = 1;
  t.out = s.dir, t.progress = false;
  const auto summary = train_mask(m, smooth_scenes(4), smooth_scenes(2), cam, t);
  CHECK_FALSE(torch::equal(before, m->U));
  CHECK(summary.gamma != Approx(t.gamma_init));  // gamma moved from its initial value
  for (const char* f : {"mask.png", "vectors.mat", "gamma.txt", "log.csv", "val.csv", "curve.png"})
    CHECK(std::filesystem::exists(s.dir / f));
  // The PNG round trip keeps the mask to 16 bits.
  const auto back = load_mask_window((s.dir / "mask.png").string(), cam);
  CHECK((back - m->window().detach()).abs().max().item<double>() < 1.0 / 65535 + 1e-6);
}

TEST_CASE("mask training resumes from its checkpoint as if never stopped, and refuses checkpoints that do not fit",
          "[mask][resume]") {
  test::Scratch s("maskresume");
  WienerCamera cam;
  cam.rows = cam.cols = 128, cam.scene = 64;
  MaskOptions mo;
  mo.elements = 31, mo.upsample = 4, mo.rows = cam.rows, mo.cols = cam.cols, mo.rank = 2;
  torch::manual_seed(3);
  const auto train = torch::rand({6, 64, 64}), val = torch::rand({2, 64, 64});
  for (const char* optimizer : {"sgd", "adam"}) {
    INFO(optimizer);
    MaskTrainOptions t;
    t.iterations = 6, t.batch = 2, t.optimizer = optimizer, t.lr = 1e-2, t.val_every = 2, t.log_every = 1;
    t.progress = false;
    t.out = s.dir / (std::string("straight_") + optimizer);
    MaskModel straight(mo);
    const auto full = train_mask(straight, train, val, cam, t);
    // The same run stopped after 4 steps (at a validation, so the logs match row for row), resumed to 6.
    t.out = s.dir / (std::string("split_") + optimizer);
    t.iterations = 4;
    MaskModel first(mo);
    train_mask(first, train, val, cam, t);
    CHECK(has_trainer_checkpoint(t.out));
    t.iterations = 6, t.resume = true;
    MaskModel second(mo);  // a fresh model: the checkpoint brings its state
    const auto resumed = train_mask(second, train, val, cam, t);
    CHECK(resumed.steps == 6);
    CHECK(torch::equal(straight->U, second->U));
    CHECK(torch::equal(straight->V, second->V));
    CHECK(resumed.gamma == full.gamma);
    CHECK(read_file_text(t.out / "val.csv") ==
          read_file_text(s.dir / (std::string("straight_") + optimizer) / "val.csv"));
    CHECK(read_file_text(t.out / "log.csv") ==
          read_file_text(s.dir / (std::string("straight_") + optimizer) / "log.csv"));
  }
  const auto run = s.dir / "split_sgd";
  MaskTrainOptions t;
  t.iterations = 8, t.batch = 2, t.val_every = 2, t.log_every = 1, t.progress = false, t.resume = true, t.out = run;
  // Another run's checkpoint (the straight run's, of the same settings) copied in: refused, naming
  // the setting that resumes it anyway; with it, the run goes on as that run.
  std::filesystem::copy_file(s.dir / "straight_sgd" / "latest.ckpt", run / "latest.ckpt",
                             std::filesystem::copy_options::overwrite_existing);
  {
    MaskModel m(mo);
    CHECK_THROWS_WITH(train_mask(m, train, val, cam, t),
                      Contains("latest.ckpt") && Contains("belongs to another run") && Contains("--force"));
    t.force = true;
    CHECK(train_mask(m, train, val, cam, t).steps == 8);
    CHECK(read_file_text(run / "run_id.txt") == read_file_text(s.dir / "straight_sgd" / "run_id.txt"));
    t.force = false;
  }
  // Another rank, another optimiser, a damaged file, NaN weights: refused, naming the file and why.
  MaskOptions rank1 = mo;
  rank1.rank = 1;
  MaskModel other(rank1);
  CHECK_THROWS_WITH(train_mask(other, train, val, cam, t), Contains("latest.ckpt") && Contains("mask.rank"));
  t.optimizer = "adam";
  MaskModel m(mo);
  CHECK_THROWS_WITH(train_mask(m, train, val, cam, t), Contains("latest.ckpt") && Contains("train.optimizer sgd"));
  t.optimizer = "sgd";
  const auto bytes = read_file_text(run / "latest.ckpt");
  write_text_atomically(run / "latest.ckpt", bytes.substr(0, bytes.size() / 2));
  CHECK_THROWS_WITH(train_mask(m, train, val, cam, t), Contains("latest.ckpt"));
  auto st = read_safetensors(s.dir / "split_adam" / "latest.ckpt");
  std::vector<std::pair<std::string, torch::Tensor>> tensors = st.tensors;
  for (auto& [name, tensor] : tensors)
    if (name == "param.U") tensor = torch::full_like(tensor, std::nan(""));
  write_safetensors(run / "latest.ckpt", tensors, st.metadata);
  t.optimizer = "adam";
  CHECK_THROWS_WITH(train_mask(m, train, val, cam, t), Contains("param.U") && Contains("NaN"));
  std::filesystem::remove(run / "latest.ckpt");
  CHECK_THROWS_WITH(train_mask(m, train, val, cam, t), Contains("nothing to resume"));
}

TEST_CASE("mask commands refuse bad input with exit code 2", "[mask][cli]") {
  test::Scratch s("maskcli");
  const auto photos = s.dir / "photos";
  std::filesystem::create_directories(photos);
  std::filesystem::copy_file(test::data_dir() / "golden" / "bsds_16052_scene.png", photos / "a.png");
  std::filesystem::copy_file(test::data_dir() / "golden" / "inet_n02980441_castle_scene.png", photos / "b.png");
  auto r = test::run_flatnet("mask eval --mask mls --images " + q(photos) + " --noise 0");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--noise"));
  write_gray16(s.dir / "small.png", torch::full({100, 100}, 65535, torch::kInt32));
  r = test::run_flatnet("mask eval --mask " + q(s.dir / "small.png") + " --images " + q(photos));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("small.png") && Contains("500x620"));
  std::filesystem::create_directories(s.dir / "empty");
  r = test::run_flatnet("mask eval --mask mls --images " + q(s.dir / "empty"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("empty"));
  r = test::run_flatnet("mask train --set mask.rank=0 --out " + q(s.dir / "o"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("mask.rank"));
  r = test::run_flatnet("mask train --set camera.noise_sigma=-1 --out " + q(s.dir / "o"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("noise_sigma"));
  r = test::run_flatnet("mask eval --mask m02 --images " + q(photos));
  INFO(r.output);
  CHECK(r.code == 0);
  CHECK_THAT(r.output, Contains("throughput 0.02"));
  // --resume: needs a checkpoint, takes the run's own config; a run is not restarted over by accident.
  const std::string tiny = " --set data.images=" + q(photos) + " --set data.val_fraction=0.5 --set train.val_count=1" +
                           " --set train.iterations=2 --set train.val_every=1 --set train.batch=1 --threads 1";
  r = test::run_flatnet("mask train --resume --out " + q(s.dir / "run"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("nothing to resume"));
  r = test::run_flatnet("mask train --out " + q(s.dir / "run") + tiny);
  INFO(r.output);
  REQUIRE(r.code == 0);
  r = test::run_flatnet("mask train --out " + q(s.dir / "run") + tiny);
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("already holds a mask training run") && Contains("--resume"));
  r = test::run_flatnet("mask train --resume --config " + q(test::source_dir() / "configs" / "mask_rank1.yaml") +
                        " --out " + q(s.dir / "run"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("own config"));
  r = test::run_flatnet("mask train --resume --set train.iterations=3 --threads 1 --out " + q(s.dir / "run"));
  INFO(r.output);
  CHECK(r.code == 0);
  CHECK_THAT(r.output, Contains("after 3 steps"));
}

TEST_CASE("separable code training: gradients move both codes and lambda, throughput held, binary codes are +-1",
          "[mask][separable]") {
  test::Scratch s("separable");
  std::filesystem::create_directories(s.dir / "photos");
  int n = 0;
  for (const char* stem :
       {"bsds_16052", "inet_n02980441_castle", "inet_n02088094_Afghan_hound", "imagen_n04356056_1392_sunglasses"})
    for (int copy = 0; copy < 3; ++copy)
      std::filesystem::copy_file(test::data_dir() / "golden" / (std::string(stem) + "_scene.png"),
                                 s.dir / "photos" / ("p" + std::to_string(n++) + ".png"));
  const auto mls_codes = test::source_dir() / "models" / "camera" / "codes_mls.mat";
  SeparableTrainOptions o;
  o.images = s.dir / "photos";
  o.init_codes = mls_codes;
  o.train_limit = 4, o.val_count = 1, o.iterations = 3, o.batch = 2, o.lr = 0.05, o.progress = false;
  o.out = s.dir / "soft";
  const auto soft = train_separable_codes(o);
  CHECK(soft.steps == 3);
  CHECK(std::abs(soft.throughput - 0.5) <= 0.05);
  CHECK(soft.lambda != Approx(o.lambda_init));  // the regulariser is learned
  MatReader start(mls_codes), learned(o.out / "codes.mat");
  const auto u0 = start.read("code_rows").flatten(), u = learned.read("code_rows").flatten();
  const auto v0 = start.read("code_cols").flatten(), v = learned.read("code_cols").flatten();
  CHECK((u - u0 * 0.95).abs().max().item<double>() > 1e-3);  // both codes moved (MLS starts at +-0.95)
  CHECK((v - v0 * 0.95).abs().max().item<double>() > 1e-3);
  CHECK(u.abs().max().item<double>() <= 1.0);
  CHECK(std::filesystem::exists(o.out / "log.csv"));
  CHECK(std::filesystem::exists(o.out / "curve.png"));

  o.binary = true;
  o.out = s.dir / "binary";
  train_separable_codes(o);
  MatReader bin(o.out / "codes.mat");
  CHECK(torch::all(bin.read("code_rows").abs() == 1).item<bool>());
  CHECK(torch::all(bin.read("code_cols").abs() == 1).item<bool>());
  // A time budget (train.minutes) stops the run early, and its codes are written as at the end.
  o.binary = false;
  o.iterations = 100000, o.minutes = 0.01 / 60;
  o.out = s.dir / "budget";
  const auto budget = train_separable_codes(o);
  CHECK(budget.steps >= 1);
  CHECK(budget.steps < 100000);
  CHECK(std::filesystem::exists(o.out / "codes.mat"));
  o.minutes = 0;
  o.iterations = 3;
  // MLS beats random codes of the same light under Tikhonov (a sanity check of the pipeline).
  const auto scenes = load_luma_scenes({s.dir / "photos" / "p0.png", s.dir / "photos" / "p3.png"}, 256, 1);
  torch::manual_seed(5);
  const auto random = torch::rand({511}, torch::kFloat64) * 2 - 1;
  CHECK(separable_psnr(u0, v0, 1e-4, scenes, 1) > separable_psnr(random, random.flip(0), 1e-4, scenes, 1));
}

TEST_CASE(
    "separable camera comparison: learned codes beat MLS under Tikhonov, less light costs PSNR, FlatNet is scored on "
    "the same captures",
    "[mask][separable][report]") {
  const auto golden = test::data_dir() / "golden";
  const std::vector<std::filesystem::path> photos = {
      golden / "bsds_16052_scene.png", golden / "inet_n02980441_castle_scene.png",
      golden / "inet_n02088094_Afghan_hound_scene.png", golden / "imagen_n04356056_1392_sunglasses_scene.png"};
  const auto mls = load_code_pair(test::source_dir() / "models" / "camera" / "codes_mls.mat");
  const auto learned = load_code_pair(test::source_dir() / "models" / "masks" / "separable" / "codes.mat");
  SeparableReportOptions o;
  o.geometry = load_camera_config(test::source_dir() / "configs" / "cameras" / "sim.yaml").raw;
  o.lambdas = {1e-4, 1e-3};
  o.light = {1.0, 1.0 / 16};
  o.tune_count = 1;
  o.progress = false;
  // FlatNet's place: a "model" that shows mid grey whatever it sees; its score must be grey's.
  CameraModel grey{[](const torch::Tensor& planes) {
                     return torch::full({planes.size(0), 3, 256, 256}, 0.5f);
                   },
                   o.geometry, "grey"};
  const auto scores = score_separable_cameras({{"MLS", mls, "shipped", grey},
                                               {"learned", learned, "shipped", std::nullopt},
                                               {"MLS again", mls, "shipped", std::nullopt}},
                                              photos, o);
  REQUIRE(scores.size() == 3);
  const auto &m = scores[0], &l = scores[1];
  INFO("MLS " << m.psnr[0] << " dB, learned " << l.psnr[0] << " dB");
  CHECK(l.psnr[0] > m.psnr[0] + 1.0);  // the target, on the golden photographs
  CHECK(l.ssim[0] > m.ssim[0]);
  for (const auto& s : scores) CHECK(s.psnr[1] < s.psnr[0]);  // 1/16 of the photons: more shot noise
  CHECK(scores[2].psnr == m.psnr);                            // the same captures for every camera: deterministic
  CHECK(scores[2].lambda_sweep_psnr == m.lambda_sweep_psnr);
  CHECK(m.lambda_sweep_psnr.size() == 2);
  CHECK(std::abs(m.throughput - 0.5) < 0.01);
  CHECK(std::abs(m.low_share_rows - 0.125) < 0.03);  // MLS: a flat spectrum
  CHECK(l.low_share_rows > 0.4);                     // the learned codes favour low frequencies
  CHECK(l.cond_p > m.cond_p);
  double grey_psnr = 0;
  for (size_t i = 1; i < photos.size(); ++i)
    grey_psnr += psnr(torch::full({3, 256, 256}, 128.0f / 255), display_scene(photos[i], 256));
  CHECK(m.flatnet_psnr == Approx(grey_psnr / 3).margin(1e-4));
  CHECK(std::isnan(l.flatnet_psnr));
  CHECK(m.scored == 3);
  const auto md = separable_section(scores, o);
  CHECK_THAT(md,
             Contains("| learned |") && Contains("not trained") && Contains("Light sweep") && Contains("cond(P1gb)"));

  o.geometry.crop[0] += 2;  // a model trained for another crop is refused, by name
  CameraModel other{grey.forward, o.geometry, "other.flatnet"};
  o.geometry.crop[0] -= 2;
  CHECK_THROWS_WITH(score_separable_cameras({{"MLS", mls, "", other}}, photos, o),
                    Contains("other.flatnet") && Contains("crop"));
}

TEST_CASE("Wiener rank-1 masks map to separable codes by the signs of their vectors", "[mask][separable]") {
  const auto mapped = codes_from_wiener_mask(test::source_dir() / "models" / "masks" / "rank1");
  CHECK(torch::all(mapped.codes.rows.abs() == 1).item<bool>());
  CHECK(mapped.codes.rows.numel() == 511);
  CHECK(mapped.agreement > 0.9);
  CHECK(mapped.agreement <= 1.0);
  CHECK_THROWS_WITH(codes_from_wiener_mask(test::source_dir() / "models" / "masks" / "rank10"), Contains("rank-1"));
}

TEST_CASE("mask report refuses bad code and model lists", "[mask][cli][report]") {
  test::Scratch s("maskreport");
  const auto photos = s.dir / "photos";
  std::filesystem::create_directories(photos);
  std::filesystem::copy_file(test::data_dir() / "golden" / "bsds_16052_scene.png", photos / "a.png");
  auto r = test::run_flatnet("mask report --images " + q(photos) + " --out " + q(s.dir / "o") + " --codes mls.mat");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--codes") && Contains("NAME=FILE"));
  r = test::run_flatnet("mask report --images " + q(photos) + " --out " + q(s.dir / "o") +
                        " --codes MLS=" + q(s.dir / "none.mat"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("none.mat"));
  r = test::run_flatnet("mask report --images " + q(photos) + " --out " + q(s.dir / "o") + " --flatnet nope=x.flatnet");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("'nope' names no code pair"));
  const auto mls = test::source_dir() / "models" / "camera" / "codes_mls.mat";
  r = test::run_flatnet("mask report --images " + q(photos) + " --out " + q(s.dir / "o") + " --codes A=" + q(mls) +
                        ",A=" + q(mls));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("names 'A' twice"));
  r = test::run_flatnet("mask report --images " + q(photos) + " --out " + q(s.dir / "o") +
                        " --codes none --flatnet MLS=x.flatnet");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--flatnet"));
  r = test::run_flatnet("mask report --images " + q(photos) + " --out " + q(photos) + " --sections separable");
  CHECK(r.code == 2);
  // The shared output rule: a folder of files flatnet did not write is not an output folder.
  CHECK_THAT(r.output, Contains("photos") && Contains("flatnet did not write"));
  r = test::run_flatnet("mask report --images " + q(photos) + " --out " + q(s.dir / "o") + " --sections lens");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--sections"));

  // One short run of the separable section with the shipped codes: 20 photographs, 2 held out.
  const char* stems[] = {"bsds_16052", "inet_n02980441_castle", "inet_n02088094_Afghan_hound",
                         "imagen_n04356056_1392_sunglasses"};
  for (int i = 0; i < 20; ++i)
    if (i > 0)
      std::filesystem::copy_file(test::data_dir() / "golden" / (std::string(stems[i % 4]) + "_scene.png"),
                                 photos / ("p" + std::to_string(i) + ".png"));
  r = test::run_flatnet("mask report --images " + q(photos) + " --out " + q(s.dir / "o") +
                        " --sections separable --tune-count 1");
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output,
             Contains("| MLS | 0.500 |") && Contains("| separable-learned |") && Contains("separable-learned binary"));
  CHECK(std::filesystem::exists(s.dir / "o" / "report.md"));
  CHECK(std::filesystem::exists(s.dir / "o" / "separable_sweep.png"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "o" / "sweep.png"));  // the Wiener sections were left out
}

TEST_CASE("mask separable takes a config like the other trainers: defaults, shortcut flags, --set, ranges",
          "[mask][separable][cli]") {
  test::Scratch s("separable_cli");
  const auto photos = test::make_photos(s.dir / "photos");
  const std::string base = "mask separable --images " + q(photos) +
                           " --set data.val_fraction=0.5 --set data.train_limit=1 --set train.val_every=1"
                           " --set train.log_every=1 --batch 1 --val-count 1";
  auto r = test::run_flatnet(base + " --iterations 2 --out " + q(s.dir / "run"));
  REQUIRE(r.code == 0);
  CHECK(std::filesystem::exists(s.dir / "run" / "codes.mat"));
  const auto config = read_file_text(s.dir / "run" / "config.yaml");
  CHECK_THAT(config, Contains("iterations: 2") && Contains("val_fraction: 0.5") && Contains("length: 511"));
  CHECK_THAT(read_file_text(s.dir / "run" / "log.csv"),
             Catch::Matchers::StartsWith("step,loss,throughput,lambda,val_psnr\n1,") && Contains("\n2,"));
  r = test::run_flatnet(base + " --set codes.target_throughput=2 --out " + q(s.dir / "bad"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("codes.target_throughput = 2") && Contains("a share of light"));
  r = test::run_flatnet(base + " --set codes.lenght=3 --out " + q(s.dir / "bad2"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("codes.length"));
  r = test::run_flatnet(base + " --init random --set codes.length=63 --iterations 1 --out " + q(s.dir / "short"));
  REQUIRE(r.code == 0);
  CHECK(MatReader(s.dir / "short" / "codes.mat").read("code_rows").numel() == 63);
  // A codes file to start from (a path, resolved as every path setting).
  r = test::run_flatnet(base + " --init " + q(s.dir / "short" / "codes.mat") + " --iterations 1 --out " +
                        q(s.dir / "from_file"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK(MatReader(s.dir / "from_file" / "codes.mat").read("code_rows").numel() == 63);
  // A mistyped --init is named before --out is claimed: no config.yaml, no lock files left behind.
  r = test::run_flatnet(base + " --init bogus --iterations 1 --out " + q(s.dir / "typo"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--init") && Contains("bogus"));
  CHECK(!std::filesystem::exists(s.dir / "typo"));
}

TEST_CASE("mask separable resumes from its checkpoint as if never stopped", "[mask][separable][cli][resume]") {
  test::Scratch s("separable_resume");
  const auto photos = test::make_photos(s.dir / "photos");
  const std::string base = "mask separable --images " + q(photos) +
                           " --set data.val_fraction=0.5 --set data.train_limit=2 --set train.val_every=2"
                           " --set train.log_every=1 --batch 1 --val-count 1 --threads 1";
  auto r = test::run_flatnet(base + " --iterations 4 --out " + q(s.dir / "straight"));
  REQUIRE(r.code == 0);
  r = test::run_flatnet(base + " --iterations 2 --out " + q(s.dir / "split"));
  REQUIRE(r.code == 0);
  r = test::run_flatnet(base + " --iterations 4 --out " + q(s.dir / "split"));  // not restarted by accident
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--resume"));
  r = test::run_flatnet("mask separable --resume --iterations 4 --threads 1 --out " + q(s.dir / "split"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("4 steps"));
  CHECK(read_file_text(s.dir / "split" / "log.csv") == read_file_text(s.dir / "straight" / "log.csv"));
  CHECK(torch::equal(MatReader(s.dir / "split" / "codes.mat").read("code_rows"),
                     MatReader(s.dir / "straight" / "codes.mat").read("code_rows")));
  CHECK(read_file_text(s.dir / "split" / "lambda.txt") == read_file_text(s.dir / "straight" / "lambda.txt"));
  // A mask trainer's checkpoint is not a code pair's.
  std::filesystem::create_directories(s.dir / "other");
  std::filesystem::copy_file(s.dir / "split" / "latest.ckpt", s.dir / "other" / "latest.ckpt");
  std::filesystem::copy_file(s.dir / "split" / "config.yaml", s.dir / "other" / "config.yaml");
  auto st = read_safetensors(s.dir / "other" / "latest.ckpt");
  st.metadata["format"] = "flatnet-mask-checkpoint";
  write_safetensors(s.dir / "other" / "latest.ckpt", st.tensors, st.metadata);
  r = test::run_flatnet("mask separable --resume --force --threads 1 --out " + q(s.dir / "other"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("latest.ckpt") && Contains("not a checkpoint of this trainer"));
}

TEST_CASE("the mask and code-pair trainers' options start where their defaults files do, and read every key",
          "[mask][config]") {
  const auto configs = test::source_dir() / "configs";
  const auto mask = Config::load({}, {}, configs / "mask_defaults.yaml");
  const auto separable = Config::load({}, {}, configs / "separable_defaults.yaml");
  for (const auto& differing :
       {defaults_differing(mask, mask_train_fields()), defaults_differing(separable, separable_train_fields())}) {
    INFO((differing.empty() ? std::string() : differing.front()));
    CHECK(differing.empty());
  }
  const auto changed =
      defaults_differing(Config::load({}, {"train.lr=0.5"}, configs / "mask_defaults.yaml"), mask_train_fields());
  REQUIRE(changed.size() == 1);
  CHECK_THAT(changed.front(), Contains("train.lr"));
  // A value is read through the table into its member, and a key the file lacks names itself.
  MaskTrainOptions o;
  read_options(Config::load({}, {"train.minutes=2.5", "train.optimizer=adam"}, configs / "mask_defaults.yaml"),
               mask_train_fields(), o);
  CHECK(o.minutes == 2.5);
  CHECK(o.optimizer == "adam");
  SeparableTrainOptions separable_options;
  CHECK_THROWS_WITH(read_options(mask, separable_train_fields(), separable_options), Contains("codes.init"));
  // A choice is a row too: read by its parser, compared with the struct's default, its error naming the key.
  MaskOptions m;
  const auto clamp = Config::load({}, {"mask.projection=clamp"}, configs / "mask_defaults.yaml");
  read_options(clamp, mask_fields(), m, "mask.");
  CHECK(m.projection == MaskProjection::clamp);
  const auto projection_changed = defaults_differing(clamp, mask_fields(), "mask.");
  REQUIRE(projection_changed.size() == 1);
  CHECK_THAT(projection_changed.front(), Contains("mask.projection"));
  CHECK_THROWS_WITH(
      read_options(Config::load({}, {"mask.init=bogus"}, configs / "mask_defaults.yaml"), mask_fields(), m, "mask."),
      Contains("mask.init") && Contains("bogus"));
  TrainOptions t;
  CHECK_THROWS_WITH(read_options(Config::load({}, {"train.schedule=linear"}), train_fields(), t),
                    Contains("train.schedule") && Contains("linear"));
  read_options(Config::load({}, {"train.schedule=cosine"}), train_fields(), t);
  CHECK(t.schedule == LrSchedule::cosine);
  // codes.init: mls is the shipped codes, random none, anything else a file next to the config that names it.
  read_options(separable, separable_train_fields(), separable_options);
  CHECK(separable_options.init_codes.filename() == "codes_mls.mat");
  read_options(Config::load({}, {"codes.init=random"}, configs / "separable_defaults.yaml"), separable_train_fields(),
               separable_options);
  CHECK(separable_options.init_codes.empty());
}

TEST_CASE(
    "the model's, data's, light's, co-design's, mask's and Wiener camera's options start where the defaults files do",
    "[mask][config]") {
  const auto configs = test::source_dir() / "configs";
  const auto train = Config::load({}, {}, configs / "defaults.yaml");
  const auto mask = Config::load({}, {}, configs / "mask_defaults.yaml");
  for (const auto& differing :
       {defaults_differing(train, model_spec_fields(), "model."),
        defaults_differing(train, light_fields(), "data.light."),
        defaults_differing(train, codesign_fields(), "codes."), defaults_differing(mask, mask_fields(), "mask."),
        defaults_differing(mask, wiener_camera_fields(), "camera."), defaults_differing(train, data_fields(), "data."),
        defaults_differing(train, perceptual_fields(), "loss."),
        defaults_differing(train, discriminator_fields(), "discriminator."),
        defaults_differing(mask, photo_split_fields())}) {
    INFO((differing.empty() ? std::string() : differing.front()));
    CHECK(differing.empty());
  }
  // A nested table reads under its prefix, and names the whole key.
  const auto changed = defaults_differing(Config::load({}, {"model.rcan.blocks=3"}, configs / "defaults.yaml"),
                                          model_spec_fields(), "model.");
  REQUIRE(changed.size() == 1);
  CHECK_THAT(changed.front(), Contains("model.rcan.blocks") && Contains("3"));
  WienerCamera cam;
  CHECK_THROWS_WITH(read_options(train, wiener_camera_fields(), cam, "camera."), Contains("camera.rows"));
}

namespace {

// One command's schema: its defaults file and every row it reads, each key prefixed as the config spells it.
struct CommandSchema {
  const char* command;  // --for of `flatnet options`
  const char* file;
  std::vector<std::pair<std::string, std::string>> rows;  // key, range meaning ("" for none)
};

template <class S>
void add_rows(CommandSchema& schema, const std::vector<OptionField<S>>& fields, const std::string& prefix = "") {
  for (const auto& f : fields) schema.rows.emplace_back(prefix + f.key, f.range);
}

std::vector<CommandSchema> command_schemas() {
  CommandSchema train{"train", "defaults.yaml", {}}, mask{"mask", "mask_defaults.yaml", {}},
      separable{"separable", "separable_defaults.yaml", {}};
  add_rows(train, train_fields());
  add_rows(train, data_fields(), "data.");
  add_rows(train, perceptual_fields(), "loss.");
  add_rows(train, light_fields(), "data.light.");
  add_rows(train, codesign_fields(), "codes.");
  add_rows(train, model_spec_fields(), "model.");
  add_rows(train, discriminator_fields(), "discriminator.");
  add_rows(mask, mask_train_fields());
  add_rows(mask, photo_split_fields());
  add_rows(mask, mask_fields(), "mask.");
  add_rows(mask, wiener_camera_fields(), "camera.");
  add_rows(separable, separable_train_fields());
  return {train, mask, separable};
}

}  // namespace

// One home per setting: each key of a command's defaults file is exactly one row of the tables that
// command reads, no row is missing from the file, and the file's comment is the setting's one doc text.
TEST_CASE("each defaults file's keys are exactly its command's rows, one row per key, each documented",
          "[mask][config]") {
  const auto configs = test::source_dir() / "configs";
  for (const auto& schema : command_schemas()) {
    const auto path = configs / schema.file;
    const auto config = Config::load({}, {}, path);
    const auto docs = setting_docs(path);
    std::map<std::string, int> rows_per_key;
    for (const auto& [key, range] : schema.rows) ++rows_per_key[key];
    for (const auto& [key, value] : config.values()) {
      INFO(schema.file << ": " << key);
      CHECK(rows_per_key[key] == 1);
      CHECK(docs.count(key) == 1);
      CHECK_FALSE((docs.count(key) && docs.at(key).empty()));
    }
    for (const auto& [key, count] : rows_per_key) {
      INFO(schema.file << ": row " << key << " is not a setting of the file");
      CHECK(config.values().count(key) == 1);
    }
  }
}

// `flatnet options` prints, for every key, the defaults file's value and comment and the row's range;
// a row whose range another table declares differently would print the wrong one.
TEST_CASE("flatnet options prints each setting's default, range and doc as its row and defaults file declare them",
          "[mask][config][cli]") {
  const auto configs = test::source_dir() / "configs";
  std::map<std::string, std::set<std::string>> ranges_of;  // every table's range meanings per key
  for (const auto& schema : command_schemas())
    for (const auto& [key, range] : schema.rows) ranges_of[key].insert(range);
  for (const auto& [key, ranges] : ranges_of) {
    INFO(key << " has " << ranges.size() << " different ranges in the tables");
    CHECK(ranges.size() == 1);
  }
  for (const auto& schema : command_schemas()) {
    const auto path = configs / schema.file;
    const auto config = Config::load({}, {}, path);
    const auto docs = setting_docs(path);
    const auto r = test::run_flatnet(std::string("options --for ") + schema.command + " --markdown");
    REQUIRE(r.code == 0);
    std::map<std::string, std::vector<std::string>> printed;  // key -> cells
    std::istringstream lines(r.output);
    for (std::string line; std::getline(lines, line);) {
      if (line.rfind("| `", 0) != 0) continue;
      std::vector<std::string> cells;
      std::string cell;
      for (size_t i = 1; i < line.size(); ++i) {
        if (line[i] == '|' && line[i - 1] != '\\') {
          cells.push_back(std::regex_replace(cell, std::regex("^ +| +$"), ""));
          cell.clear();
        } else {
          cell += line[i];
        }
      }
      REQUIRE(cells.size() == 4);
      printed[cells[0].substr(1, cells[0].size() - 2)] = cells;
    }
    for (const auto& [key, range] : schema.rows) {
      INFO(schema.command << ": " << key);
      REQUIRE(printed.count(key) == 1);
      const auto& cells = printed.at(key);
      const auto value = config.str(key).empty() ? std::string("\"\"") : config.str(key);
      CHECK(cells[1] == "`" + value + "`");
      CHECK(cells[2] == range);
      CHECK(std::regex_replace(cells[3], std::regex("\\\\\\|"), "|") == docs.at(key));
    }
    CHECK(printed.size() == config.values().size());
  }
  // A flag's --help is the same text: the key and its comment in the command's defaults file.
  const auto docs = setting_docs(configs / "separable_defaults.yaml");
  const auto help = test::run_flatnet("mask separable --help");
  CHECK_THAT(help.output, Contains("codes.init: " + docs.at("codes.init").substr(0, 30)));
  CHECK_THAT(help.output, Contains("--minutes"));
}

// The struct defaults, the rows and the file agree, and a range declared by a row is checked at load.
TEST_CASE("every setting of the defaults files is bound by an option table's row", "[mask][config]") {
  const auto configs = test::source_dir() / "configs";
  // Rows name their keys for errors and make path keys; a member no row binds is a programming error.
  CHECK(train_key(&TrainOptions::crop) == "train.crop");
  CHECK(model_key<&ModelSpec::unet, &UNetOptions::width>() == "model.unet.width");
  CHECK(data_key(&DataOptions::camera) == "data.camera");
  CHECK(discriminator_key(&DiscriminatorOptions::width) == "discriminator.width");
  CHECK_THROWS_AS(train_key(&TrainOptions::bf16), std::logic_error);
  CHECK(Config::is_path_key("data.camera"));
  CHECK(Config::is_path_key("loss.vgg_file"));
  CHECK(Config::is_path_key("codes.init"));
  CHECK_FALSE(Config::is_path_key("train.batch"));
  CHECK_FALSE(Config::is_path_key("data.source"));
  // A range declared only by a train row still refuses a config (io/config.cpp holds no table).
  CHECK_THROWS_WITH(Config::load({}, {"train.batch=0"}, configs / "defaults.yaml"),
                    Contains("train.batch") && Contains("1 to 4096 samples"));
  CHECK_THROWS_WITH(Config::load({}, {"discriminator.width=0"}, configs / "defaults.yaml"),
                    Contains("discriminator.width") && Contains("1 to 4096 filters"));
}
