// The GAN trainer and its data: deterministic batches, bit-for-bit resume, NaN handling, and
// data-parallel training over c10d/Gloo on 127.0.0.1.
#include "catch_torch.hpp"

#include <arpa/inet.h>
#include <cmath>
#include <fstream>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include "core/error.hpp"
#include "core/util.hpp"
#include "helpers.hpp"
#include "io/safetensors.hpp"
#include "nn/checkpoint.hpp"
#include "train/csv_log.hpp"
#include "train/distributed.hpp"
#include "train/gan_trainer.hpp"
#include "train/nonfinite.hpp"

#include <iomanip>
#include <sstream>
#include <thread>
#include <unistd.h>

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

// Random pairs held in memory (20x24 measurements, 16x16 scenes); item i is the same every time.
class MemoryPairs : public PairSource {
 public:
  // poison: every measurement NaN; poisoned_item >= 0: only that item's.
  explicit MemoryPairs(int64_t n, bool poison = false, int64_t poisoned_item = -1)
      : n_(n), poison_(poison), poisoned_item_(poisoned_item) {}
  int64_t size() const override { return n_; }
  Sample load(int64_t i, int64_t) const override {
    auto gen = at::detail::createCPUGenerator(static_cast<uint64_t>(i) + 1);
    Sample s{at::randn({4, 20, 24}, gen), at::rand({3, 16, 16}, gen), "item" + std::to_string(i)};
    if (poison_ || i == poisoned_item_) s.meas.fill_(std::numeric_limits<float>::quiet_NaN());
    return s;
  }

 private:
  int64_t n_;
  bool poison_;
  int64_t poisoned_item_;
};

struct Setup {
  Config config = Config::load(
      {}, {"model.unet.width=2", "model.inversion.init=random", "discriminator.width=4", "loss.perceptual=0"});
  CameraConfig camera;
  Setup() {
    camera.raw.crop = {0, 0, 20, 24};
    camera.scene_size = 16;
  }
  TrainOptions options(const std::filesystem::path& out, int64_t iterations) const {
    TrainOptions t;
    t.iterations = iterations;
    t.batch = 2;
    t.val_every = 2;
    t.out = out;
    t.progress = false;
    t.w_perceptual = 0;
    t.noise_augment = 0.01;
    return t;
  }
  GanTrainer trainer(const std::filesystem::path& out, int64_t iterations, bool poison = false,
                     int64_t poisoned_item = -1) const {
    torch::manual_seed(0);
    Generator g(generator_options(config, camera, true));
    Discriminator d(discriminator_options(config));
    auto train = std::make_shared<MemoryPairs>(6, poison, poisoned_item);
    auto val = load_all(MemoryPairs(2), 0, 1);
    return GanTrainer(g, d, Vgg16Features(nullptr), train, val, options(out, iterations),
                      model_identity(config, camera));
  }
};

std::map<std::string, torch::Tensor> weights(const std::filesystem::path& checkpoint) {
  auto m = model_from_checkpoint(checkpoint);
  std::map<std::string, torch::Tensor> out;
  for (const auto& p : m.generator->named_parameters()) out[p.key()] = p.value().clone();
  for (const auto& b : m.generator->named_buffers()) out[b.key()] = b.value().clone();
  return out;
}

}  // namespace

TEST_CASE("batch loader: batches depend only on (seed, step), across epochs and threads", "[train]") {
  auto src = std::make_shared<MemoryPairs>(5);
  LoaderOptions a;
  a.batch = 3, a.seed = 7, a.workers = 2;
  BatchLoader from_start(src, a);
  std::vector<Batch> seq;
  for (int i = 0; i < 4; ++i) seq.push_back(from_start.next());
  a.first_step = 2, a.workers = 1;
  BatchLoader resumed(src, a);
  CHECK(torch::equal(resumed.next().meas, seq[2].meas));
  CHECK(torch::equal(resumed.next().gt, seq[3].gt));
  // Every item appears once per epoch: steps 0..4 of batch 3 cover 3 epochs of 5.
  const auto perm = epoch_permutation(5, 7, 1);
  CHECK(std::set<int64_t>(perm.begin(), perm.end()).size() == 5);
}

TEST_CASE("training resumes bit for bit from its checkpoint", "[train]") {
  test::Scratch s("resume");
  Setup setup;
  {
    auto straight = setup.trainer(s.dir / "straight", 4);
    const auto summary = straight.run();
    CHECK(summary.last_step == 4);
  }
  {
    auto first = setup.trainer(s.dir / "split", 2);
    first.run();
  }
  {
    auto second = setup.trainer(s.dir / "split", 4);
    second.resume(s.dir / "split" / "latest.ckpt");
    second.run();
  }
  const auto a = weights(s.dir / "straight" / "latest.ckpt"), b = weights(s.dir / "split" / "latest.ckpt");
  REQUIRE(a.size() == b.size());
  for (const auto& [name, t] : a) {
    INFO(name);
    CHECK(torch::equal(t, b.at(name)));
  }
  // The logs continue without duplicated steps, and validation scores the same weights: the
  // straight run's second validation must see its updated weights (channels-last + GEMM
  // upsampling once cached a stale copy of the first validation's up-convolution weights).
  const auto lines = read_lines(s.dir / "split" / "val.csv");
  CHECK(lines.size() == 3);  // header, step 2, step 4
  const auto straight_lines = read_lines(s.dir / "straight" / "val.csv");
  REQUIRE(straight_lines.size() == 3);
  auto scores = [](const std::string& line) {  // without the seconds column (the fourth)
    size_t third = 0;
    for (int comma = 0; comma < 3; ++comma) third = line.find(',', third) + 1;
    return line.substr(0, third) + line.substr(line.find(',', third) + 1);
  };
  CHECK(scores(straight_lines[1]) == scores(lines[1]));
  CHECK(scores(straight_lines[2]) == scores(lines[2]));
  CHECK(std::filesystem::exists(s.dir / "split" / "model.flatnet"));
  CHECK(std::filesystem::exists(s.dir / "split" / "samples.png"));
}

TEST_CASE("checkpoints as a set: a kill between best.ckpt and latest.ckpt loses nothing", "[train][safe]") {
  test::Scratch s("ckpt_set");
  Setup setup;
  const auto dir = s.dir / "run";
  {
    auto first = setup.trainer(dir, 2);
    first.run();
  }
  const auto step2 = s.dir / "latest_step2.ckpt";
  std::filesystem::copy_file(dir / "latest.ckpt", step2);
  {
    auto second = setup.trainer(dir, 4);
    second.resume(dir / "latest.ckpt");
    second.run();
  }
  // As if killed after best.ckpt and before latest.ckpt: latest is a step behind the best file.
  std::filesystem::copy_file(step2, dir / "latest.ckpt", std::filesystem::copy_options::overwrite_existing);
  const double best_on_disk = checkpoint_best_psnr(dir / "best.ckpt");
  auto third = setup.trainer(dir, 4);
  const auto said = third.resume(dir / "latest.ckpt");
  std::ostringstream best;
  best << std::fixed << std::setprecision(2) << best_on_disk;
  CHECK_THAT(said,
             Contains("resumed at step 2") && Contains("both optimisers") && Contains(best.str() + " dB (best.ckpt)"));
  // model.flatnet follows the checkpoint resumed from, not the lost steps.
  const auto model = weights(dir / "latest.ckpt");
  auto exported = load_model_file(dir / "model.flatnet");
  for (const auto& p : exported.generator->named_parameters()) CHECK(torch::equal(p.value(), model.at(p.key())));
  const auto summary = third.run();
  CHECK(summary.best_psnr >= best_on_disk);
  CHECK(checkpoint_best_psnr(dir / "best.ckpt") == summary.best_psnr);
}

TEST_CASE("validation scores the current weights, never a cached copy", "[train]") {
  Setup setup;
  torch::manual_seed(0);
  Generator g(generator_options(setup.config, setup.camera, true));
  g->prepare_training({false, true, false, true});  // channels-last + GEMM upsampling, as training uses
  const auto val = load_all(MemoryPairs(2), 0, 1);
  const auto before = validate(g, val, 2);
  {
    torch::NoGradGuard no_grad;
    for (auto& p : g->named_parameters())
      if (p.key().find(".up.") != std::string::npos) p.value().mul_(-3.0);  // change only the up-convolutions
  }
  const auto after = validate(g, val, 2);
  CHECK(before.psnr != after.psnr);
}

TEST_CASE("validation under several lights weighs each condition alike and reports each one's PSNR", "[train]") {
  Setup setup;
  torch::manual_seed(0);
  Generator g(generator_options(setup.config, setup.camera, true));
  auto val = load_all(MemoryPairs(3), 0, 1);
  val[2].condition = 1;  // two display samples, one dim
  std::vector<double> alone;
  for (const auto& sample : val) alone.push_back(validate(g, {sample}, 1).psnr);
  const auto r = validate(g, val, 2);
  REQUIRE(r.condition_psnr.size() == 3);
  CHECK(r.condition_psnr[0] == Approx((alone[0] + alone[1]) / 2).epsilon(1e-5));
  CHECK(r.condition_psnr[1] == Approx(alone[2]).epsilon(1e-5));
  CHECK(std::isnan(r.condition_psnr[2]));
  CHECK(r.psnr == Approx(((alone[0] + alone[1]) / 2 + alone[2]) / 2).epsilon(1e-5));
  // One condition only: the plain mean, as before.
  val[2].condition = 0;
  CHECK(validate(g, val, 2).psnr == Approx((alone[0] + alone[1] + alone[2]) / 3).epsilon(1e-5));
}

TEST_CASE("the non-finite guard runs before any optimiser step, discriminator warm-up included", "[train]") {
  Setup setup;
  torch::manual_seed(0);
  Generator g(generator_options(setup.config, setup.camera, true));
  Discriminator d(discriminator_options(setup.config));
  Vgg16Features none(nullptr);
  torch::optim::Adam opt_g(g->parameters(), 1e-2), opt_d(d->parameters(), 1e-2);
  MemoryPairs poisoned(2, true);
  Batch b{torch::stack({poisoned.load(0, 0).meas, poisoned.load(1, 0).meas}),
          torch::stack({poisoned.load(0, 0).gt, poisoned.load(1, 0).gt}), 0};
  auto snapshot = [](torch::nn::Module& m) {
    std::vector<torch::Tensor> out;
    for (const auto& p : m.parameters()) out.push_back(p.detach().clone());
    return out;
  };
  const auto g0 = snapshot(*g), d0 = snapshot(*d);
  for (int64_t warmup : {0, 5}) {
    auto t = setup.options("", 1);
    t.w_adversarial = 0.5;
    t.discriminator_warmup = warmup;  // 5: step 0 trains only the discriminator
    CHECK_THROWS_AS(gan_step(g, d, none, opt_g, opt_d, t, b, 0), NonFiniteStep);
    const auto g1 = snapshot(*g), d1 = snapshot(*d);
    for (size_t i = 0; i < g0.size(); ++i) CHECK(torch::equal(g0[i], g1[i]));
    for (size_t i = 0; i < d0.size(); ++i) CHECK(torch::equal(d0[i], d1[i]));
  }
}

TEST_CASE(
    "each weight-free perceptual term alone trains the whole generator, feature matching trains the "
    "discriminator too",
    "[train][loss]") {
  Setup setup;
  MemoryPairs pairs(2);
  Batch b{torch::stack({pairs.load(0, 0).meas, pairs.load(1, 0).meas}),
          torch::stack({pairs.load(0, 0).gt, pairs.load(1, 0).gt}), 0};
  Vgg16Features none(nullptr);
  for (const std::string term : {"feature_matching", "frequency", "chroma", "gradient"}) {  // NOLINT
    INFO(term);
    torch::manual_seed(0);
    Generator g(generator_options(setup.config, setup.camera, true));
    Discriminator d(discriminator_options(setup.config));
    torch::optim::SGD opt_g(g->parameters(), 1e-2), opt_d(d->parameters(), 1e-2);
    auto t = setup.options("", 1);
    t.w_mse = 0, t.w_adversarial = 0;  // the term alone
    double TrainOptions::*weight = term == "feature_matching" ? &TrainOptions::w_feature_matching
                                   : term == "frequency"      ? &TrainOptions::w_frequency
                                   : term == "chroma"         ? &TrainOptions::w_chroma
                                                              : &TrainOptions::w_gradient;
    t.*weight = 1.0;
    std::vector<torch::Tensor> g0, d0;
    for (const auto& p : g->parameters()) g0.push_back(p.detach().clone());
    for (const auto& p : d->parameters()) d0.push_back(p.detach().clone());
    const auto l = gan_step(g, d, none, opt_g, opt_d, t, b, 0);
    CHECK(l.loss > 0);
    const double logged = term == "feature_matching" ? l.feature_matching
                          : term == "frequency"      ? l.frequency
                          : term == "chroma"         ? l.chroma
                                                     : l.gradient;
    CHECK(logged == Approx(l.loss));
    const auto params = g->named_parameters();
    for (size_t i = 0; i < g0.size(); ++i) {
      const auto& name = params[i].key();
      INFO(name);
      // A convolution's bias right before a training-mode batch norm has no effect (the norm
      // subtracts the batch mean): its gradient is 0 under any loss. Every other parameter moves.
      const bool before_batch_norm = name.size() > 12 && (name.compare(name.size() - 12, 12, ".conv.0.bias") == 0 ||
                                                          name.compare(name.size() - 12, 12, ".conv.3.bias") == 0);
      // The gradient, not the step: a small term moves deep weights by less than float resolution.
      const auto& grad = params[i].value().grad();
      if (!before_batch_norm) CHECK((grad.defined() && grad.abs().sum().item<double>() > 0));
    }
    bool d_moved = false;
    const auto d_params = d->parameters();
    for (size_t i = 0; i < d0.size(); ++i) d_moved = d_moved || !torch::equal(d0[i], d_params[i]);
    CHECK(d_moved == (term == "feature_matching"));
  }
}

TEST_CASE("schedules: halving steps down, cosine falls smoothly to 0 at the last step", "[train]") {
  TrainOptions t;
  t.lr_halve_every = 10;
  CHECK(lr_factor(t, 9) == 1.0);
  CHECK(lr_factor(t, 25) == 0.25);
  t.schedule = LrSchedule::cosine;
  t.iterations = 100;
  CHECK(lr_factor(t, 0) == Approx(1.0));
  CHECK(lr_factor(t, 50) == Approx(0.5));
  CHECK(lr_factor(t, 100) == Approx(0.0).margin(1e-12));
  CHECK(lr_factor(t, 75) < lr_factor(t, 74));
  CHECK_THROWS_WITH(parse_lr_schedule("linear"), Contains("halving or cosine"));
}

TEST_CASE("a time budget: cosine spans it, training stops cleanly with a checkpoint, resume continues it",
          "[train][budget]") {
  TrainOptions t;
  t.schedule = LrSchedule::cosine;
  t.iterations = 1000000;
  t.minutes = 10;
  CHECK(lr_factor(t, 5, 0) == Approx(1.0));
  CHECK(lr_factor(t, 5, 300) == Approx(0.5));  // half the budget: half way down the cosine
  CHECK(lr_factor(t, 5, 600) == Approx(0.0).margin(1e-12));
  CHECK(lr_factor(t, 5, 6000) == Approx(0.0).margin(1e-12));

  test::Scratch s("budget");
  Setup setup;
  auto make = [&](double minutes) {
    torch::manual_seed(0);
    auto opts = setup.options(s.dir / "run", 1000000);
    opts.minutes = minutes;
    opts.val_every = 1000000;
    Generator g(generator_options(setup.config, setup.camera, true));
    Discriminator d(discriminator_options(setup.config));
    return GanTrainer(g, d, Vgg16Features(nullptr), std::make_shared<MemoryPairs>(6), load_all(MemoryPairs(2), 0, 1),
                      opts, model_identity(setup.config, setup.camera));
  };
  int64_t first_steps = 0;
  {
    auto trainer = make(0.01);  // 0.6 s
    const auto summary = trainer.run();
    CHECK(summary.budget_reached);
    first_steps = summary.last_step;
    CHECK(first_steps > 0);
    CHECK(first_steps < 1000000);
  }
  REQUIRE(std::filesystem::exists(s.dir / "run" / "latest.ckpt"));
  CHECK(std::filesystem::exists(s.dir / "run" / "model.flatnet"));
  // The budget counts the time of earlier runs: the same budget again stops at once; a larger one continues.
  {
    auto again = make(0.01);
    again.resume(s.dir / "run" / "latest.ckpt");
    const auto summary = again.run();
    CHECK(summary.last_step == first_steps);
  }
  {
    auto more = make(0.2);
    more.resume(s.dir / "run" / "latest.ckpt");
    CHECK(more.run().last_step > first_steps);
  }
}

TEST_CASE(
    "crops: corners depend on (seed, step) and stay inside the scene, and crop training runs and validates at full "
    "size",
    "[train]") {
  TrainOptions t;
  t.crop = 16;
  t.seed = 3;
  const auto a = crop_corners(t, 4, 64, 7), b = crop_corners(t, 4, 64, 7), c = crop_corners(t, 4, 64, 8);
  CHECK(a == b);
  CHECK(a != c);
  for (const auto& [r, col] : a) CHECK((r >= 0 && col >= 0 && r + 16 <= 64 && col + 16 <= 64));
  CHECK(crop_corners(t, 4, 16, 0).empty());  // a crop of the whole scene is no crop
  test::Scratch s("crop");
  Setup setup;
  setup.camera.scene_size = 32;
  setup.camera.raw.crop = {0, 0, 36, 40};
  torch::manual_seed(0);
  Generator g(generator_options(setup.config, setup.camera, true));
  Discriminator d(discriminator_options(setup.config));
  class Pairs32 : public PairSource {
   public:
    int64_t size() const override { return 4; }
    Sample load(int64_t i, int64_t) const override {
      auto gen = at::detail::createCPUGenerator(static_cast<uint64_t>(i) + 1);
      return {at::randn({4, 36, 40}, gen), at::rand({3, 32, 32}, gen), "p" + std::to_string(i)};
    }
  };
  auto opt = setup.options(s.dir / "run", 2);
  opt.crop = 16;
  GanTrainer trainer(g, d, Vgg16Features(nullptr), std::make_shared<Pairs32>(), load_all(Pairs32(), 0, 1), opt,
                     model_identity(setup.config, setup.camera));
  const auto summary = trainer.run();
  CHECK(summary.last_step == 2);
  CHECK(std::isfinite(summary.last_psnr));
}

TEST_CASE("EMA: the average follows the weights with the warmed-up decay, is checkpointed, resumed and exported",
          "[train]") {
  test::Scratch s("ema");
  Setup setup;
  auto make = [&](const std::filesystem::path& out, int64_t iterations) {
    torch::manual_seed(0);
    Generator g(generator_options(setup.config, setup.camera, true));
    Discriminator d(discriminator_options(setup.config));
    auto opt = setup.options(out, iterations);
    opt.ema_decay = 0.9;
    return GanTrainer(g, d, Vgg16Features(nullptr), std::make_shared<MemoryPairs>(6), load_all(MemoryPairs(2), 0, 1),
                      opt, model_identity(setup.config, setup.camera));
  };
  {
    auto straight = make(s.dir / "straight", 4);
    straight.run();
    // The exported weights are the average, which differs from the live ones.
    bool used_average = false;
    auto m = model_from_checkpoint(s.dir / "straight" / "latest.ckpt", &used_average);
    CHECK(used_average);
    auto exported = m.generator->named_parameters();
    auto& average = straight.exported();
    for (const auto& p : average->named_parameters()) CHECK(torch::equal(p.value(), exported[p.key()]));
  }
  {
    auto first = make(s.dir / "split", 2);
    first.run();
  }
  {
    auto second = make(s.dir / "split", 4);
    second.resume(s.dir / "split" / "latest.ckpt");
    second.run();
  }
  const auto a = weights(s.dir / "straight" / "latest.ckpt"), b = weights(s.dir / "split" / "latest.ckpt");
  for (const auto& [name, t] : a) {
    INFO(name);
    CHECK(torch::equal(t, b.at(name)));
  }
  // One update by hand: avg <- d avg + (1 - d) w with d = min(0.9, (1 + step) / (10 + step)).
  torch::manual_seed(1);
  Generator g(generator_options(setup.config, setup.camera, true));
  WeightAverage ema(g, 0.9);
  const auto w0 = g->parameters()[0].detach().clone();
  {
    torch::NoGradGuard no_grad;
    g->parameters()[0].add_(1.0);
  }
  ema.update(0);  // d = 0.1
  CHECK(torch::allclose(ema.average()->parameters()[0], w0 + 0.9, 1e-5, 1e-6));
}

TEST_CASE("refresh_batch_norm: each layer's statistics become the plain mean over the batches, whatever they were",
          "[train]") {
  Setup setup;
  auto source = std::make_shared<MemoryPairs>(6);
  const auto opt = setup.options({}, 1);
  auto loader = [&](int64_t first_step) {
    LoaderOptions lo;
    lo.batch = opt.batch;
    lo.first_step = first_step;
    lo.noise_augment = opt.noise_augment;
    return std::make_unique<BatchLoader>(source, lo);
  };
  auto refreshed = [&](int64_t first_step, int64_t batches, bool garbage) {
    torch::manual_seed(0);
    Generator g(generator_options(setup.config, setup.camera, true));
    if (garbage) {  // statistics the refresh must forget
      torch::NoGradGuard no_grad;
      for (auto& b : g->buffers()) b.fill_(7);
    }
    g->eval();  // as validation and export hold it
    refresh_batch_norm(g, *loader(first_step), batches, opt);
    std::map<std::string, torch::Tensor> stats;
    for (const auto& b : g->named_buffers()) stats[b.key()] = b.value().clone();
    return std::make_pair(g, stats);
  };
  auto [g, both] = refreshed(0, 2, /*garbage=*/true);
  const auto first = refreshed(0, 1, false).second, second = refreshed(1, 1, false).second;
  int64_t layers = 0;
  for (const auto& [name, t] : both) {
    INFO(name);
    if (name.find("num_batches_tracked") != std::string::npos) {
      CHECK(t.item<int64_t>() == 2);
      continue;
    }
    ++layers;
    // In training mode a layer normalises by its batch's statistics, so each batch's contribution
    // is independent of the running values: the mean over two batches is the mean of the two.
    CHECK(torch::allclose(t, (first.at(name) + second.at(name)) / 2, 1e-4, 1e-5));
    CHECK_FALSE(torch::allclose(t, torch::full_like(t, 7)));
  }
  CHECK(layers >= 4);                      // the BatchNorm between the stages and the U-Net's
  for (const auto& m : g->modules(false))  // the momentum is put back
    if (auto* bn = dynamic_cast<torch::nn::BatchNorm2dImpl*>(m.get())) CHECK(bn->options.momentum().has_value());
  CHECK_FALSE(g->is_training());  // left in the mode it was found in
  CHECK_THROWS_WITH(refresh_batch_norm(g, *loader(0), 0, opt), Contains("train.bn_refresh"));
}

TEST_CASE("train.bn_refresh changes what is validated and exported, never the training", "[train]") {
  test::Scratch s("bn_refresh");
  Setup setup;
  auto run = [&](const std::string& name, int64_t refresh) {
    torch::manual_seed(0);
    Generator g(generator_options(setup.config, setup.camera, true));
    Discriminator d(discriminator_options(setup.config));
    auto opt = setup.options(s.dir / name, 4);
    opt.bn_refresh = refresh;
    GanTrainer t(g, d, Vgg16Features(nullptr), std::make_shared<MemoryPairs>(6), load_all(MemoryPairs(2), 0, 1), opt,
                 model_identity(setup.config, setup.camera));
    return t.run();
  };
  const auto plain = run("plain", 0), refreshed = run("refreshed", 3);
  CHECK(plain.last_step == refreshed.last_step);
  const auto a = weights(s.dir / "plain" / "latest.ckpt"), b = weights(s.dir / "refreshed" / "latest.ckpt");
  bool statistics_differ = false;
  for (const auto& [name, t] : a) {
    INFO(name);
    const bool statistic = name.find("running_") != std::string::npos || name.find("num_batches") != std::string::npos;
    if (statistic)
      statistics_differ = statistics_differ || !torch::equal(t, b.at(name));
    else
      CHECK(torch::equal(t, b.at(name)));  // the same steps: the refresh draws its own batches
  }
  CHECK(statistics_differ);
  CHECK(plain.last_psnr != refreshed.last_psnr);
  CHECK_THROWS_WITH(Config::load({}, {"train.bn_refresh=-1"}), Contains("train.bn_refresh"));
}

TEST_CASE("train.keep_every keeps the exported model at those steps, and export --average-of takes their mean",
          "[train][average]") {
  test::Scratch s("keep_every");
  Setup setup;
  torch::manual_seed(0);
  Generator g(generator_options(setup.config, setup.camera, true));
  Discriminator d(discriminator_options(setup.config));
  auto opt = setup.options(s.dir / "run", 8);
  opt.keep_every = 4;  // validations at 2, 4, 6, 8: kept at 4 and 8
  GanTrainer t(g, d, Vgg16Features(nullptr), std::make_shared<MemoryPairs>(6), load_all(MemoryPairs(2), 0, 1), opt,
               model_identity(setup.config, setup.camera));
  t.run();
  const auto kept = s.dir / "run" / "kept";
  CHECK(std::filesystem::exists(kept / "step4.flatnet"));
  CHECK(std::filesystem::exists(kept / "step8.flatnet"));
  CHECK_FALSE(std::filesystem::exists(kept / "step2.flatnet"));
  CHECK_FALSE(std::filesystem::exists(kept / "step6.flatnet"));
  // The last kept one is the run's model.flatnet; the earlier one is another set of weights.
  const auto last = load_model_file(kept / "step8.flatnet"),
             final_model = load_model_file(s.dir / "run" / "model.flatnet");
  const auto first = load_model_file(kept / "step4.flatnet");
  CHECK(last.provenance.trained_steps == "8");
  CHECK(first.provenance.trained_steps == "4");
  const auto mean = average_models({kept / "step4.flatnet", kept / "step8.flatnet"});
  for (const auto& p : final_model.generator->named_parameters()) {
    INFO(p.key());
    CHECK(torch::equal(p.value(), last.generator->named_parameters()[p.key()]));
    const auto expect = (first.generator->named_parameters()[p.key()] + p.value()) / 2;
    CHECK(torch::allclose(mean.generator->named_parameters()[p.key()], expect, 1e-6, 1e-7));
  }
  CHECK_THROWS_WITH(Config::load({}, {"train.keep_every=-1"}), Contains("train.keep_every"));
}

TEST_CASE("a run's kept/ that is a link is never written through", "[train][average][hostile]") {
  test::Scratch s("keep_through_link");
  Setup setup;
  std::filesystem::create_directories(s.dir / "run");
  std::filesystem::create_directories(s.dir / "elsewhere");
  std::filesystem::create_directory_symlink(s.dir / "elsewhere", s.dir / "run" / "kept");
  torch::manual_seed(0);
  Generator g(generator_options(setup.config, setup.camera, true));
  Discriminator d(discriminator_options(setup.config));
  auto opt = setup.options(s.dir / "run", 2);
  opt.keep_every = 2;
  GanTrainer t(g, d, Vgg16Features(nullptr), std::make_shared<MemoryPairs>(6), load_all(MemoryPairs(2), 0, 1), opt,
               model_identity(setup.config, setup.camera));
  CHECK_THROWS_WITH(t.run(), Contains("kept") && Contains("is a link"));
  CHECK(std::filesystem::is_empty(s.dir / "elsewhere"));
}

TEST_CASE("NaN losses in a row stop training with a clear message and keep the last checkpoint", "[train]") {
  test::Scratch s("nan");
  Setup setup;
  auto t = setup.trainer(s.dir / "run", 4, /*poison=*/true);
  CHECK_THROWS_WITH(t.run(), Contains("diverged") && Contains("latest.ckpt") &&
                                 Contains(std::to_string(kNonFiniteLimit) + " non-finite step(s) in a row"));
  // A validation between the skipped steps saves the weights as they were: none took a bad step.
  REQUIRE(std::filesystem::exists(s.dir / "run" / "latest.ckpt"));
  for (const auto& [name, w] : weights(s.dir / "run" / "latest.ckpt")) {
    INFO(name);
    CHECK(torch::isfinite(w).all().item<bool>());
  }
}

TEST_CASE("one non-finite step is skipped: no weight or batch-norm statistic takes it, training goes on", "[train]") {
  test::Scratch s("nan_once");
  Setup setup;
  // Six items, batch 2: one step in three holds the poisoned item, never two in a row.
  auto t = setup.trainer(s.dir / "run", 6, false, /*poisoned_item=*/3);
  const auto summary = t.run();
  CHECK(summary.last_step == 6);
  CHECK(std::isfinite(summary.last_psnr));
  for (const auto& [name, w] : weights(s.dir / "run" / "latest.ckpt")) {
    INFO(name);
    CHECK(torch::isfinite(w).all().item<bool>());
  }
}

TEST_CASE("the non-finite guard: skips count, a good step starts the count again, the limit stops", "[train]") {
  NonFiniteGuard guard("RUN/latest.ckpt", "a lower train.lr");
  for (int round = 0; round < 3; ++round) {
    for (int64_t i = 0; i + 1 < kNonFiniteLimit; ++i) CHECK_NOTHROW(guard.skip(NonFiniteStep("loss", NAN, i)));
    guard.good();
  }
  CHECK(guard.skipped() == 3 * (kNonFiniteLimit - 1));
  for (int64_t i = 0; i + 1 < kNonFiniteLimit; ++i) guard.skip(NonFiniteStep("loss", NAN, i));
  CHECK_THROWS_WITH(guard.skip(NonFiniteStep("generator loss (mse 0.1)", NAN, 7)),
                    Contains("the generator loss (mse 0.1) is nan at step 7") && Contains("RUN/latest.ckpt") &&
                        Contains("a lower train.lr"));
  CHECK(all_finite({torch::ones(3), torch::Tensor()}));
  CHECK_FALSE(all_finite({torch::tensor({1.0f, INFINITY})}));
}

// ---- Data-parallel training (c10d, Gloo over 127.0.0.1) -------------------------------------------

namespace {

// A TCP port the kernel says is free now (bind to port 0, read it back, release it).
int free_port() {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  REQUIRE(fd >= 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  addr.sin_port = 0;
  socklen_t len = sizeof(addr);
  const bool ok = ::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) == 0 &&
                  ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len) == 0;
  ::close(fd);
  REQUIRE(ok);
  return ntohs(addr.sin_port);
}

// Runs fn(rank, group) on `world` threads, each with its own ProcessGroup; rethrows the first error.
// fn must not use Catch2's assertions (not thread-safe; ThreadSanitizer reports them): return
// results to the test's thread and check them there.
void with_ranks(int world, const std::function<void(int, ProcessGroup&)>& fn) {
  const int port = free_port();
  std::vector<std::thread> threads;
  std::vector<std::exception_ptr> errors(world);
  for (int r = 0; r < world; ++r)
    threads.emplace_back([&, r] {
      try {
        DistributedOptions o;
        o.world_size = world, o.rank = r, o.master_port = port, o.timeout_s = 30;
        ProcessGroup group(o);
        fn(r, group);
      } catch (...) {
        errors[r] = std::current_exception();
      }
    });
  for (auto& t : threads) t.join();
  for (auto& e : errors)
    if (e) std::rethrow_exception(e);
}

}  // namespace

TEST_CASE("distributed: two ranks start from rank 0's weights and hold bit-identical parameters after every step",
          "[train][dist]") {
  test::Scratch s("dist_sync");
  Setup setup;
  std::vector<Generator> gens;
  std::vector<Discriminator> discs;
  std::vector<std::unique_ptr<GanTrainer>> trainers;
  for (int r = 0; r < 2; ++r) {
    torch::manual_seed(100 + r);  // different initialisations: the broadcast must fix them
    gens.emplace_back(generator_options(setup.config, setup.camera, true));
    discs.emplace_back(discriminator_options(setup.config));
    auto opt = setup.options(s.dir / ("rank" + std::to_string(r)), 3);
    opt.check_sync_every = 1;  // the trainer compares checksums across ranks after every step
    trainers.push_back(std::make_unique<GanTrainer>(gens[r], discs[r], Vgg16Features(nullptr),
                                                    std::make_shared<MemoryPairs>(6), load_all(MemoryPairs(2), 0, 1),
                                                    opt, model_identity(setup.config, setup.camera)));
  }
  bool differ = false;
  for (const auto& p : gens[0]->named_parameters())
    differ = differ || !torch::equal(p.value(), gens[1]->named_parameters()[p.key()]);
  CHECK(differ);
  std::vector<int64_t> last_steps(2, -1);  // Catch2's assertions are not thread-safe: check after the join
  with_ranks(2, [&](int r, ProcessGroup& group) {
    trainers[r]->set_distributed(&group);
    last_steps[r] = trainers[r]->run().last_step;
  });
  CHECK(last_steps == std::vector<int64_t>{3, 3});
  const auto a = gens[0]->named_parameters(), b = gens[1]->named_parameters();
  for (const auto& p : a) {
    INFO(p.key());
    CHECK(torch::equal(p.value(), b[p.key()]));
  }
  for (const auto& p : discs[0]->named_parameters())
    CHECK(torch::equal(p.value(), discs[1]->named_parameters()[p.key()]));
  CHECK(std::filesystem::exists(s.dir / "rank0" / "latest.ckpt"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "rank1"));  // only rank 0 writes
}

TEST_CASE("distributed: with batch norm in eval mode, two ranks at batch 2 equal one process at batch 4",
          "[train][dist]") {
  Setup setup;
  torch::manual_seed(5);
  Generator reference(generator_options(setup.config, setup.camera, true));
  Discriminator disc(discriminator_options(setup.config));
  auto clone = [&] {
    Generator g(generator_options(setup.config, setup.camera, true));
    torch::NoGradGuard no_grad;
    for (auto& p : g->named_parameters()) p.value().copy_(reference->named_parameters()[p.key()]);
    for (auto& b : g->named_buffers()) b.value().copy_(reference->named_buffers()[b.key()]);
    g->eval();  // BN with running statistics: a sample's gradient does not depend on its batch mates
    return g;
  };
  TrainOptions t = setup.options("", 1);
  t.w_adversarial = 0;
  MemoryPairs data(4);
  Batch all;
  std::vector<torch::Tensor> meas, gt;
  for (int i = 0; i < 4; ++i) meas.push_back(data.load(i, 0).meas), gt.push_back(data.load(i, 0).gt);
  all.meas = torch::stack(meas), all.gt = torch::stack(gt);
  Vgg16Features none(nullptr);

  auto single = clone();
  torch::optim::SGD sgd_single(single->parameters(), 0.1), sgd_d(disc->parameters(), 0.1);
  for (int step = 0; step < 2; ++step) gan_step(single, disc, none, sgd_single, sgd_d, t, all, step);

  std::vector<Generator> ranks{clone(), clone()};
  with_ranks(2, [&](int r, ProcessGroup& group) {
    torch::optim::SGD sgd(ranks[r]->parameters(), 0.1), unused(disc->parameters(), 0.1);
    Batch half{all.meas.slice(0, 2 * r, 2 * r + 2), all.gt.slice(0, 2 * r, 2 * r + 2), 0};
    for (int step = 0; step < 2; ++step) gan_step(ranks[r], disc, none, sgd, unused, t, half, step, &group);
  });
  double worst = 0;
  for (const auto& p : single->named_parameters())
    for (int r = 0; r < 2; ++r)
      worst = std::max(worst, (p.value() - ranks[r]->named_parameters()[p.key()]).abs().max().item<double>());
  CHECK(worst < 1e-5);
  // ... and the steps did change the weights, so the agreement is not that of untouched copies.
  const auto before = clone();
  double moved = 0;
  for (const auto& p : single->named_parameters())
    moved = std::max(moved, (p.value() - before->named_parameters()[p.key()]).abs().max().item<double>());
  CHECK(moved > 1e-4);
}

TEST_CASE("distributed: the sampler gives each rank its slice of the global batch", "[train][dist]") {
  auto src = std::make_shared<MemoryPairs>(7);
  LoaderOptions one;
  one.batch = 4, one.seed = 3;
  BatchLoader global(src, one);
  LoaderOptions r0 = one, r1 = one;
  r0.batch = r1.batch = 2;
  r0.world_size = r1.world_size = 2;
  r1.rank = 1;
  BatchLoader a(src, r0), b(src, r1);
  for (int step = 0; step < 3; ++step) {  // across an epoch boundary (7 items)
    const auto g = global.next(), x = a.next(), y = b.next();
    CHECK(torch::equal(torch::cat({x.meas, y.meas}), g.meas));
  }
}

TEST_CASE("distributed: bad rendezvous settings are refused clearly", "[train][dist]") {
  setenv("WORLD_SIZE", "2", 1);
  setenv("RANK", "2", 1);
  CHECK_THROWS_WITH(distributed_from_env(), Contains("RANK") && Contains("outside [0, WORLD_SIZE=2)"));
  setenv("RANK", "x", 1);
  CHECK_THROWS_WITH(distributed_from_env(), Contains("RANK='x' is not an integer"));
  unsetenv("WORLD_SIZE");
  unsetenv("RANK");
  CHECK(distributed_from_env().world_size == 1);
}

TEST_CASE("a trainer's CSV log: header at once, rows on flush, a failed write names the file", "[train][logs]") {
  test::Scratch s("csv_log");
  CsvLog log(s.dir / "log.csv", "step,loss,psnr");
  CHECK(read_file_text(s.dir / "log.csv", 1 << 20) == "step,loss,psnr\n");
  log.add(10, 0.25, 18.5);
  log.add(20, 0.125, std::nan(""));
  CHECK(read_file_text(s.dir / "log.csv", 1 << 20) == "step,loss,psnr\n");  // not yet flushed
  log.flush();
  CHECK(read_file_text(s.dir / "log.csv", 1 << 20) == "step,loss,psnr\n10,0.25,18.5\n20,0.125,nan\n");
  for (const auto& e : std::filesystem::directory_iterator(s.dir))  // no temporary file left behind
    CHECK(e.path().filename() == "log.csv");
  std::ofstream(s.dir / "file") << "x";
  CHECK_THROWS_WITH(CsvLog(s.dir / "file" / "log.csv", "step"), Contains("log.csv"));
}

TEST_CASE("the moving average's decay is checked once per entry: the config's range, the trainer's options",
          "[train][errors]") {
  CHECK_THROWS_WITH(Config::load({}, {"train.ema_decay=1"}), Contains("train.ema_decay = 1"));
  Setup setup;
  test::Scratch s("ema_decay");
  torch::manual_seed(0);
  Generator g(generator_options(setup.config, setup.camera, true));
  Discriminator d(discriminator_options(setup.config));
  for (const double bad : {-0.5, 1.0}) {
    auto o = setup.options(s.dir / "run", 2);
    o.ema_decay = bad;
    CHECK_THROWS_WITH(GanTrainer(g, d, Vgg16Features(nullptr), std::make_shared<MemoryPairs>(6),
                                 load_all(MemoryPairs(2), 0, 1), o, model_identity(setup.config, setup.camera)),
                      Contains("train.ema_decay: must lie in [0, 1)"));
  }
}

TEST_CASE("a checkpoint whose best PSNR is not a number exports no model", "[train][safe][hostile]") {
  test::Scratch s("ckpt_best_text");
  Setup setup;
  const auto dir = s.dir / "run";
  {
    auto first = setup.trainer(dir, 2);
    first.run();
  }
  CHECK_NOTHROW(model_from_checkpoint(dir / "best.ckpt"));
  auto st = read_safetensors(dir / "best.ckpt");
  REQUIRE(st.metadata.count("best_psnr"));
  st.metadata["best_psnr"] = "abc";
  write_safetensors(s.dir / "edited.ckpt", st.tensors, st.metadata);
  CHECK_THROWS_WITH(model_from_checkpoint(s.dir / "edited.ckpt"),
                    Contains("edited.ckpt") && Contains("best_psnr") && Contains("not a number"));
}
