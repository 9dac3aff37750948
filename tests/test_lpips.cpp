// LPIPS v0.1 (src/nn/lpips.hpp): against a Python reference on files written the way torchvision and
// the lpips package write them, its search for the weight files, refusals naming the file, and the
// `flatnet eval --lpips` column (absent files: one line, the other metrics still run).
#include "catch_torch.hpp"

#include <cstdlib>
#include <fstream>

#include "core/error.hpp"
#include "helpers.hpp"
#include "io/image.hpp"
#include "io/torch_file.hpp"
#include "nn/lpips.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;
using test::q;

namespace {

// The files of a randomly initialised LPIPS, written by this project's torch.save writer in the
// layouts of torchvision (features.N.*) and of the lpips package (linK.model.1.weight).
LpipsFiles write_random_lpips(Lpips& model, const std::filesystem::path& dir, const std::string& trunk_name,
                              const std::string& linear_name) {
  std::filesystem::create_directories(dir);
  std::vector<std::pair<std::string, torch::Tensor>> trunk, linear;
  torch::NoGradGuard no_grad;
  for (auto& p : model->named_parameters()) {
    if (p.key().rfind("features.", 0) == 0) {
      p.value().normal_(0, 0.05);
      trunk.emplace_back(p.key(), p.value());
    } else {
      p.value().uniform_(0, 1);
      linear.emplace_back(p.key() + ".model.1.weight", p.value());
    }
  }
  save_torch_state_dict(dir / trunk_name, trunk);
  save_torch_state_dict(dir / linear_name, linear);
  return {dir / trunk_name, dir / linear_name};
}

// Sets an environment variable for one scope (the search looks in torch hub's cache).
struct ScopedEnv {
  std::string name;
  ScopedEnv(const std::string& n, const std::string& value) : name(n) { setenv(n.c_str(), value.c_str(), 1); }
  ~ScopedEnv() { unsetenv(name.c_str()); }
};

}  // namespace

TEST_CASE("LPIPS equals the Python reference on torchvision's and lpips' file layouts", "[lpips][python][solo]") {
  if (!test::python_has_torch()) SKIP_TEST("/usr/bin/python3 has no torch");
  test::Scratch s("lpips_py");
  const auto script = test::source_dir() / "scripts" / "lpips_reference.py";
  const auto r = test::run_shell("/usr/bin/python3 " + q(script) + " make " + q(s.dir) + " 3");
  INFO(r.output);
  REQUIRE(r.code == 0);
  const auto cases = read_torch_file(s.dir / "cases.pt");
  const auto x = cases->get("x")->tensor, y = cases->get("y")->tensor;  // {3,3,64,64}; y[2] == x[2]
  for (const auto backbone : {LpipsBackbone::alex, LpipsBackbone::vgg}) {
    const auto name = lpips_backbone_name(backbone);
    INFO(name);
    // The files as a user has them: the backbone in torch.save's legacy container (as torchvision's
    // files are, with the classifier's tensors), the linear layers in the zip container.
    const auto files = find_lpips_files(backbone, s.dir);
    CHECK(files.linear.filename() == name + ".pth");
    auto lpips = load_lpips(backbone, files);
    torch::NoGradGuard no_grad;
    const auto mine = lpips->forward(x, y), reference = cases->get(name)->tensor;  // {3}
    CHECK(mine.sizes() == reference.sizes());
    CHECK((mine - reference).abs().max().item<double>() < 1e-5 * reference.abs().max().item<double>() + 1e-7);
    CHECK(mine[0].item<double>() > 0.01);
    CHECK(mine[2].item<double>() == Approx(0).margin(1e-7));
  }
}

TEST_CASE("LPIPS: a distance (zero on equal images, symmetric), and its files round-trip", "[lpips]") {
  test::Scratch s("lpips");
  torch::manual_seed(5);
  Lpips model(LpipsBackbone::alex);
  const auto files = write_random_lpips(model, s.dir / "w", "alexnet-owt-7be5be79.pth", "alex.pth");
  auto loaded = load_lpips(LpipsBackbone::alex, files);
  const auto x = torch::rand({2, 3, 48, 48}), y = torch::rand({2, 3, 48, 48});
  torch::NoGradGuard no_grad;
  const auto d = loaded->forward(x, y);
  CHECK(d.sizes() == torch::IntArrayRef{2});
  CHECK(torch::allclose(d, model->forward(x, y)));
  CHECK(torch::allclose(d, loaded->forward(y, x)));
  CHECK((d > 0).all().item<bool>());
  CHECK(loaded->forward(x, x).abs().max().item<double>() < 1e-7);
  // A little noise is closer than another image altogether.
  CHECK((loaded->forward(x, (x + 0.02 * torch::randn_like(x)).clamp(0, 1)) < d).all().item<bool>());
  // Five feature maps, at AlexNet's channels.
  const auto f = loaded->features(x * 2 - 1);
  REQUIRE(f.size() == 5);
  CHECK(f[0].size(1) == 64);
  CHECK(f[4].size(1) == 256);
}

TEST_CASE("LPIPS: missing files say which to get and where, bad files are refused naming them", "[lpips]") {
  test::Scratch s("lpips_bad");
  const ScopedEnv hub("TORCH_HOME", (s.dir / "torch_home").string());
  std::filesystem::create_directories(s.dir / "empty");
  CHECK_THROWS_WITH(find_lpips_files(LpipsBackbone::vgg, s.dir / "empty"),
                    Contains("vgg16-397923af.pth") && Contains("vgg.pth") && Contains("empty") &&
                        Contains("torch_home/hub/checkpoints") && Contains("PerceptualSimilarity"));
  CHECK_THROWS_WITH(parse_lpips_backbone("squeeze"), Contains("alex or vgg"));
  // The backbone found in torch hub's cache, the linear layers in the given folder.
  torch::manual_seed(1);
  Lpips model(LpipsBackbone::alex);
  write_random_lpips(model, s.dir / "torch_home" / "hub" / "checkpoints", "alexnet-owt-7be5be79.pth", "unused.pth");
  write_random_lpips(model, s.dir / "mine", "unused.pth", "alex.pth");
  const auto found = find_lpips_files(LpipsBackbone::alex, s.dir / "mine");
  CHECK(found.backbone == s.dir / "torch_home" / "hub" / "checkpoints" / "alexnet-owt-7be5be79.pth");
  CHECK(found.linear == s.dir / "mine" / "alex.pth");

  // Linear layers of the wrong width (VGG's file given for AlexNet).
  Lpips vgg(LpipsBackbone::vgg);
  const auto vgg_files = write_random_lpips(vgg, s.dir / "vgg", "vgg16-397923af.pth", "vgg.pth");
  CHECK_THROWS_WITH(load_lpips(LpipsBackbone::alex, {found.backbone, vgg_files.linear}),
                    Contains("vgg.pth") && Contains("lin1.model.1.weight") && Contains("wrong shape"));
  // A backbone file of the other network.
  CHECK_THROWS_WITH(load_lpips(LpipsBackbone::alex, {vgg_files.backbone, found.linear}),
                    Contains("vgg16-397923af.pth") && Contains("features.0.weight"));
  // A file that is not torch.save's, and one holding NaN.
  std::ofstream(s.dir / "junk.pth") << "not a pickle";
  CHECK_THROWS_WITH(load_lpips(LpipsBackbone::alex, {found.backbone, s.dir / "junk.pth"}), Contains("junk.pth"));
  save_torch_state_dict(s.dir / "nan.pth", {{"lin0.model.1.weight", torch::full({1, 64, 1, 1}, NAN)}});
  CHECK_THROWS_WITH(load_lpips(LpipsBackbone::alex, {found.backbone, s.dir / "nan.pth"}),
                    Contains("nan.pth") && Contains("lin0.model.1.weight") && Contains("NaN"));
}

TEST_CASE("flatnet eval --lpips: a column with the files, one line and the other metrics without", "[lpips][cli]") {
  test::Scratch s("lpips_eval");
  const auto gt = s.dir / "gt", rec = s.dir / "rec" / "noisy";
  std::filesystem::create_directories(gt);
  std::filesystem::create_directories(rec);
  torch::manual_seed(2);
  for (const char* name : {"a.png", "b.png"}) {
    const auto truth = torch::rand({3, 64, 64});
    write_rgb8(gt / name, truth);
    write_rgb8(rec / name, (truth + 0.1 * torch::randn_like(truth)).clamp(0, 1));
  }
  Lpips model(LpipsBackbone::alex);
  write_random_lpips(model, s.dir / "w", "alexnet-owt-7be5be79.pth", "alex.pth");
  auto r = test::run_flatnet("eval --niqe none --gt " + q(gt) + " --out " + q(s.dir / "rec") +
                             " --lpips alex --lpips-dir " + q(s.dir / "w"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("LPIPS alex"));
  std::ifstream csv(s.dir / "rec" / "metrics.csv");
  std::string header;
  std::getline(csv, header);
  CHECK(header == "image,method,psnr,ssim,mean_output,mean_truth,colour_kept,detail_kept,lpips_alex,stripes");
  std::ifstream json(s.dir / "rec" / "scores.json");
  const std::string scores((std::istreambuf_iterator<char>(json)), {});
  CHECK_THAT(scores, Contains("\"lpips_net\": \"alex\""));

  // Without the files: one line naming them, exit 0, the other columns.
  r = test::run_shell("TORCH_HOME=" + q(s.dir / "no_hub") + " " + std::string(FLATNET_BINARY) +
                      " eval --niqe none --gt " + q(gt) + " --out " + q(s.dir / "rec") + " --lpips vgg --lpips-dir " +
                      q(s.dir / "w"));
  CHECK(r.code == 0);
  CHECK_THAT(r.output, Contains("no LPIPS column") && Contains("vgg16-397923af.pth") && Contains("vgg.pth"));
  CHECK_THAT(r.output, Contains("noisy") && !Contains("LPIPS vgg"));
  r = test::run_flatnet("eval --gt " + q(gt) + " --out " + q(s.dir / "rec") + " --lpips squeeze");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--lpips") && Contains("alex or vgg"));
}
