// The GAN trainer and its data: deterministic batches, bit-for-bit resume, NaN handling.
#include <catch2/catch.hpp>

#include "core/error.hpp"
#include "core/util.hpp"
#include "helpers.hpp"
#include "train/gan_trainer.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

// Random pairs held in memory (20x24 measurements, 16x16 scenes); item i is the same every time.
class MemoryPairs : public PairSource {
 public:
  explicit MemoryPairs(int64_t n, bool poison = false) : n_(n), poison_(poison) {}
  int64_t size() const override { return n_; }
  Sample load(int64_t i, int64_t) const override {
    auto gen = at::detail::createCPUGenerator(static_cast<uint64_t>(i) + 1);
    Sample s{at::randn({4, 20, 24}, gen), at::rand({3, 16, 16}, gen), "item" + std::to_string(i)};
    if (poison_) s.meas.fill_(std::numeric_limits<float>::quiet_NaN());
    return s;
  }

 private:
  int64_t n_;
  bool poison_;
};

struct Setup {
  Config config = Config::load({}, {"model.unet.width=2", "model.inversion.init=random", "discriminator.width=4",
                                    "loss.perceptual=0"});
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
  GanTrainer trainer(const std::filesystem::path& out, int64_t iterations, bool poison = false) const {
    torch::manual_seed(0);
    Generator g(generator_options(config, camera, true));
    Discriminator d(discriminator_options(config));
    auto train = std::make_shared<MemoryPairs>(6, poison);
    auto val = load_all(MemoryPairs(2), 0, 1);
    return GanTrainer(g, d, Vgg16Features(nullptr), train, val, options(out, iterations), config, camera);
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
  // The logs continue without duplicated steps.
  const auto lines = read_lines(s.dir / "split" / "val.csv");
  CHECK(lines.size() == 3);  // header, step 2, step 4
  CHECK(std::filesystem::exists(s.dir / "split" / "model.flatnet"));
  CHECK(std::filesystem::exists(s.dir / "split" / "samples.png"));
}

TEST_CASE("a NaN loss stops training with a clear message and keeps the last checkpoint", "[train]") {
  test::Scratch s("nan");
  Setup setup;
  auto t = setup.trainer(s.dir / "run", 4, /*poison=*/true);
  CHECK_THROWS_WITH(t.run(), Contains("diverged") && Contains("latest.ckpt"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "run" / "latest.ckpt"));  // nothing saved from a bad step
}
