// Networks, losses, configs and model files: shapes, gradients, names, round trips, errors.
#include "catch_torch.hpp"
#include <fstream>
#include <map>
#include <sstream>

#include <ATen/autocast_mode.h>

#include "core/error.hpp"
#include "core/precision.hpp"
#include "eval/metrics.hpp"
#include "io/image.hpp"
#include "helpers.hpp"
#include "tiny_model.hpp"
#include "nn/generator.hpp"
#include "nn/fused_adam.hpp"
#include "nn/onednn_conv.hpp"
#include "nn/losses.hpp"
#include "io/config.hpp"
#include "nn/checkpoint.hpp"
#include "nn/model_file.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

// A generator small enough for unit tests: 20x24 measurements -> 16x16 scene, U-Net width 2.
GeneratorOptions tiny_options(int64_t k = 1, Enhancer e = Enhancer::unet) {
  GeneratorOptions o;
  o.rows = 20, o.cols = 24, o.scene = 16;
  o.inversion.phil = torch::randn({20, 16, k}) * 0.2;
  o.inversion.phir = torch::randn({24, 16, k}) * 0.2;
  o.enhancer = e;
  o.unet.width = 2;
  o.dncnn.layers = 4, o.dncnn.width = 4;
  o.rcan.groups = 2, o.rcan.blocks = 2, o.rcan.width = 16, o.rcan.reduction = 2;
  o.nafnet.width = 4;
  return o;
}

}  // namespace

TEST_CASE("U-Net has FlatNet's structure and parameter names", "[nn]") {
  UNet net(UNetOptions{4, 3, 2, 0.99});
  const auto out = net->forward(torch::randn({2, 4, 32, 32}));
  CHECK(out.sizes() == torch::IntArrayRef({2, 3, 32, 32}));
  auto params = net->named_parameters();
  // Names as in FlatNet's models.py, so state dicts interchange.
  for (const char* name : {"inc.conv.conv.0.weight", "inc.conv.conv.1.weight", "down1.mpconv.0.conv.0.weight",
                           "down4.mpconv.0.conv.3.weight", "up1.up.weight", "up1.conv.conv.0.weight",
                           "up4.conv.conv.4.bias", "outc.conv.weight"}) {
    INFO(name);
    CHECK(params.find(name) != nullptr);
  }
  // Widths: w, 2w, 4w, 8w, 8w down; up1 takes 16w channels and gives 4w.
  CHECK(params["down3.mpconv.0.conv.0.weight"].sizes() == torch::IntArrayRef({16, 8, 3, 3}));
  CHECK(params["down4.mpconv.0.conv.0.weight"].sizes() == torch::IntArrayRef({16, 16, 3, 3}));
  CHECK(params["up1.up.weight"].sizes() == torch::IntArrayRef({16, 16, 2, 2}));
  CHECK(params["up1.conv.conv.0.weight"].sizes() == torch::IntArrayRef({8, 32, 3, 3}));
  // Stride-2 first conv in the down blocks.
  auto bn = net->named_modules()["inc.conv.conv.1"]->as<torch::nn::BatchNorm2dImpl>();
  REQUIRE(bn);
  CHECK(bn->options.momentum().value() == Approx(0.99));
}

TEST_CASE("inversion computes leaky_relu(PhiL^T Y PhiR) per channel, in FlatNet's channel order", "[nn]") {
  for (int64_t k : {1, 4}) {
    auto o = tiny_options(k);
    FlatInversion inv(o.inversion);
    const auto Y = torch::randn({2, 4, 20, 24});
    const auto X = inv->forward(Y);
    REQUIRE(X.sizes() == torch::IntArrayRef({2, 4, 16, 16}));
    for (int c = 0; c < 4; ++c) {
      const int64_t j = k == 1 ? 0 : c;
      const auto L = o.inversion.phil.select(2, j), R = o.inversion.phir.select(2, j);
      const auto expected = torch::leaky_relu(torch::matmul(L.t(), torch::matmul(Y.select(1, c), R)), 0.01);
      CHECK(torch::allclose(X.select(1, 3 - c), expected, 1e-4, 1e-5));  // output is (r, gr, gb, b)
    }
  }
}

TEST_CASE("gradients reach every parameter of every generator variant and the discriminators", "[nn]") {
  torch::manual_seed(0);
  for (auto e : {Enhancer::unet, Enhancer::dncnn, Enhancer::rcan, Enhancer::nafnet}) {
    for (int64_t k : {1, 4}) {
      Generator g(tiny_options(k, e));
      // NAFNet's blocks start as the identity (beta = gamma = 0), which gives their inner layers no
      // gradient at step 0; any other value does.
      for (auto& p : g->named_parameters())
        if (p.key().size() > 5 &&
            (p.key().substr(p.key().size() - 5) == ".beta" || p.key().substr(p.key().size() - 6) == ".gamma")) {
          torch::NoGradGuard no_grad;
          p.value().fill_(0.1);
        }
      const auto out = g->forward(torch::randn({2, 4, 20, 24}));
      REQUIRE(out.sizes() == torch::IntArrayRef({2, 3, 16, 16}));
      CHECK(out.min().item<double>() >= 0);
      CHECK(out.max().item<double>() <= 1);
      test::check_all_gradients(*g, (out - 0.3).pow(2).mean());
    }
  }
  for (const char* kind : {"thesis", "flatnet"}) {
    Discriminator d(DiscriminatorOptions{kind, 4});
    const auto logits = d->forward(torch::rand({3, 3, 32, 32}));
    REQUIRE(logits.sizes() == torch::IntArrayRef({3, 1}));
    test::check_all_gradients(*d, logits.sum());
  }
  CHECK_THROWS_WITH(Discriminator(DiscriminatorOptions{"patch", 4}), Contains("thesis or flatnet"));
}

TEST_CASE("NAFNet: the authors' parameter names and shapes, blocks that start as the identity, LayerNorm2d",
          "[nn][nafnet]") {
  NAFNet net(NAFNetOptions{8, 3, 4, 1, 1, 2});
  const auto params = net->named_parameters();
  // NAFNet_arch.py's names (basicsr), so that its state dicts map onto this module.
  for (const char* name : {"intro.weight", "encoders.0.0.conv1.weight", "encoders.0.0.norm1.weight",
                           "encoders.0.0.sca.1.weight", "encoders.3.0.beta", "downs.3.weight", "middle_blks.0.gamma",
                           "ups.0.0.weight", "decoders.3.1.conv5.bias", "ending.weight"}) {
    INFO(name);
    CHECK(params.find(name) != nullptr);
  }
  CHECK(params["encoders.0.0.conv2.weight"].sizes() == torch::IntArrayRef({8, 1, 3, 3}));  // depthwise over 2c
  CHECK(params["downs.0.weight"].sizes() == torch::IntArrayRef({8, 4, 2, 2}));             // 2x2 stride 2 to 2c
  CHECK(params["ups.0.0.weight"].sizes() == torch::IntArrayRef({128, 64, 1, 1}));          // 1x1 to 2c, then shuffle
  CHECK(params.find("ups.0.0.bias") == nullptr);
  CHECK(params["encoders.3.0.conv1.weight"].sizes() == torch::IntArrayRef({64, 32, 1, 1}));
  const auto out = net->forward(torch::randn({2, 8, 32, 48}));
  CHECK(out.sizes() == torch::IntArrayRef({2, 3, 32, 48}));
  CHECK_THROWS_WITH(net->forward(torch::randn({1, 8, 24, 32})), Contains("multiples of 16"));
  // LayerNorm2d normalises each pixel over its channels.
  LayerNorm2d ln(5);
  const auto x = torch::randn({2, 5, 3, 4}) * 3 + 1;
  const auto y = ln->forward(x);
  CHECK(y.mean(1).abs().max().item<double>() < 1e-5);
  CHECK(torch::allclose(y.var(1, false), torch::ones({2, 3, 4}), 1e-3, 1e-3));
}

TEST_CASE("naive generator: the Tikhonov stage equals the SVD closed form", "[nn]") {
  auto o = tiny_options();
  o.input = InputStage::tikhonov;
  const auto P = torch::randn({4, 20, 16}, torch::kFloat64), Q = torch::randn({4, 24, 16}, torch::kFloat64);
  o.tik_P = P, o.tik_Q = Q, o.tik_lambda = 1e-3;
  Generator g(o);
  // Noise-free measurement of a known scene; with a small lambda the first stage recovers it.
  const auto X = torch::rand({1, 4, 16, 16}, torch::kFloat64);
  const auto Y = torch::matmul(P, torch::matmul(X, Q.transpose(1, 2))).to(torch::kFloat32);
  const auto rec = g->first_stage(Y).flip({1});
  CHECK(torch::allclose(rec, X.to(torch::kFloat32), 1e-2, 1e-2));
  test::check_all_gradients(*g, g->forward(torch::cat({Y, Y * 0.5})).mean());  // the Tikhonov stage holds buffers only
}

TEST_CASE("VGG-16 features: torchvision's layout, loader round trip, clear error without weights", "[nn]") {
  Vgg16Features vgg;
  auto params = vgg->named_parameters();
  CHECK(params.size() == 20);  // 10 convolutions up to relu4_3
  CHECK(params["features.0.weight"].sizes() == torch::IntArrayRef({64, 3, 3, 3}));
  CHECK(params["features.21.weight"].sizes() == torch::IntArrayRef({512, 512, 3, 3}));
  const auto [r22, r43] = vgg->forward(torch::rand({1, 3, 32, 32}));
  CHECK(r22.sizes() == torch::IntArrayRef({1, 128, 16, 16}));
  CHECK(r43.sizes() == torch::IntArrayRef({1, 512, 4, 4}));
  for (const auto& p : params) CHECK_FALSE(p.value().requires_grad());

  test::Scratch s("vgg");
  c10::Dict<std::string, at::Tensor> dict;
  for (const auto& p : params) dict.insert(p.key(), torch::randn(p.value().sizes()));
  const auto bytes = torch::pickle_save(c10::IValue(dict));
  std::ofstream(s.dir / "vgg.pt", std::ios::binary).write(bytes.data(), bytes.size());
  auto loaded = load_vgg16(s.dir / "vgg.pt");
  CHECK(torch::equal(loaded->named_parameters()["features.21.weight"], dict.at("features.21.weight")));
  CHECK_THROWS_WITH(load_vgg16(s.dir / "missing.pt"), Contains("loss.perceptual = 0"));
  std::ofstream(s.dir / "junk.pt") << "not a tensor file";
  CHECK_THROWS_WITH(load_vgg16(s.dir / "junk.pt"), Contains("junk.pt"));
}

TEST_CASE("config: defaults, base files, --set, unknown keys with a suggestion, round trip", "[config]") {
  test::Scratch s("config");
  std::ofstream(s.dir / "base.yaml") << "model:\n  unet:\n    width: 16\ntrain:\n  lr: 2.0e-4\n";
  std::ofstream(s.dir / "exp.yaml") << "base: base.yaml\ntrain:\n  lr: 5.0e-4\n";
  auto c = Config::load(s.dir / "exp.yaml", {"train.batch=2"});
  CHECK(c.integer("model.unet.width") == 16);
  CHECK(c.num("train.lr") == Approx(5e-4));
  CHECK(c.integer("train.batch") == 2);
  CHECK(c.num("loss.perceptual") == Approx(1.2));  // untouched default
  CHECK_THROWS_WITH(Config::load(s.dir / "exp.yaml", {"train.itrations=5"}),
                    Contains("unknown setting 'train.itrations'") && Contains("train.iterations"));
  // Far from every key: no guess, the section's keys instead (a guess like 'data.images' misleads).
  CHECK_THROWS_WITH(Config::load(s.dir / "exp.yaml", {"train.optimiser_kind=adam"}),
                    Contains("unknown setting 'train.optimiser_kind'") && !Contains("did you mean") &&
                        Contains("train settings: ") && Contains("iterations") && !Contains("unet"));
  CHECK_THROWS_WITH(Config::load(s.dir / "exp.yaml", {"colour.saturation=2"}),
                    Contains("`flatnet options` lists them"));
  CHECK(nearest_key("lr", {"train.lr", "data.images"}) == "train.lr");
  CHECK(nearest_key("train.optimizer", {"train.lr", "data.images"}).empty());
  std::ofstream(s.dir / "bad.yaml") << "model:\n  unet:\n    widht: 3\n";
  CHECK_THROWS_WITH(Config::load(s.dir / "bad.yaml"), Contains("bad.yaml") && Contains("model.unet.width"));
  CHECK_THROWS_WITH(Config::load(s.dir / "exp.yaml", {"train.batch=four"}).integer("train.batch"),
                    Contains("train.batch"));
  const auto again = Config::from_text(c.to_yaml(), "text");
  CHECK(again.to_yaml() == c.to_yaml());  // paths are written resolved, so the text is a fixed point
}

TEST_CASE("model files and state dicts round trip, and wrong files give clear errors", "[nn][model]") {
  test::Scratch s("model");
  auto config = Config::load({}, {"model.unet.width=2"});
  const auto camera = test::tiny_camera();
  auto g = test::random_generator(config, camera);  // non-trivial running statistics
  const auto Y = torch::randn({1, 4, 20, 24});
  const auto expected = g->forward(Y);

  save_model_file(s.dir / "m.flatnet", g, config, camera);
  auto m = load_model_file(s.dir / "m.flatnet");
  CHECK(torch::equal(m.generator->forward(Y), expected));
  CHECK(m.camera.raw.crop == camera.raw.crop);

  export_state_dict(s.dir / "sd.pt", g);
  Generator h(generator_options(config, camera, false));
  import_state_dict(s.dir / "sd.pt", h);
  h->eval();
  CHECK(torch::equal(h->forward(Y), expected));

  // Wrong architecture, wrong kind of file, not a file at all.
  auto wide = Config::load({}, {"model.unet.width=3"});
  Generator w(generator_options(wide, camera, false));
  CHECK_THROWS_WITH(import_state_dict(s.dir / "sd.pt", w), Contains("sd.pt") && Contains("the model needs"));
  CHECK_THROWS_WITH(load_model_file(s.dir / "sd.pt"), Contains("sd.pt") && Contains("not a flatnet"));
  std::ofstream(s.dir / "junk.flatnet") << "junk";
  CHECK_THROWS_WITH(load_model_file(s.dir / "junk.flatnet"), Contains("junk.flatnet"));
  CHECK_THROWS_WITH(load_model_file(s.dir / "none.flatnet"), Contains("no such file"));
  // One damaged byte inside a weight's data: found by the zip entry's CRC-32 (LibTorch's reader
  // would load it); the same for a state dict read by `flatnet import`.
  for (const char* name : {"m.flatnet", "sd.pt"}) {
    INFO(name);
    std::ifstream in(s.dir / name, std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), {});
    const auto phil = g->named_parameters()["inversion.PhiL"].contiguous();
    const std::string needle(static_cast<const char*>(phil.data_ptr()), 64);
    const auto at = bytes.find(needle);
    REQUIRE(at != std::string::npos);
    bytes[at + 10] ^= 0x01;
    const auto damaged = s.dir / (std::string("damaged_") + name);
    std::ofstream(damaged, std::ios::binary) << bytes;
    Generator d(generator_options(config, camera, false));
    if (std::string(name) == "m.flatnet") {
      CHECK_THROWS_WITH(load_model_file(damaged), Contains("damaged_m.flatnet") && Contains("CRC-32"));
    } else {
      CHECK_THROWS_WITH(import_state_dict(damaged, d), Contains("damaged_sd.pt") && Contains("CRC-32"));
    }
  }
  // A weight that is NaN (a damaged or diverged file) is refused by name, not run into black images.
  {
    torch::NoGradGuard ng;
    g->named_parameters()["enhancer.outc.conv.weight"][0][0][0][0] = std::nan("");
  }
  save_model_file(s.dir / "nan.flatnet", g, config, camera);
  CHECK_THROWS_WITH(load_model_file(s.dir / "nan.flatnet"),
                    Contains("nan.flatnet") && Contains("enhancer.outc.conv.weight") && Contains("NaN"));
}

TEST_CASE("the C++ generator equals a Python reference of FlatNet-sep on the same weights", "[nn][python][solo]") {
  if (std::system("/usr/bin/python3 -c 'import torch' >/dev/null 2>&1") != 0) {
    SKIP_TEST("/usr/bin/python3 has no torch");
  }
  test::Scratch s("pyref");
  const auto script = test::source_dir() / "scripts" / "flatnet_reference.py";
  auto config = Config::load({}, {"model.unet.width=4", "model.inversion.shared=false"});
  CameraConfig camera;  // the real sizes: 500x620 -> 256x256
  for (int64_t k : {1, 4}) {
    INFO("k = " << k);
    const std::string ks = std::to_string(k);
    // Python makes weights, input and output; C++ imports them and must agree.
    auto cmd = "/usr/bin/python3 '" + script.string() + "' make '" + (s.dir / "sd.pt").string() + "' '" +
               (s.dir / "in.pt").string() + "' '" + (s.dir / "out.pt").string() + "' 4 " + ks + " >/dev/null";
    REQUIRE(std::system(cmd.c_str()) == 0);
    auto c =
        Config::load({}, {"model.unet.width=4", std::string("model.inversion.shared=") + (k == 1 ? "true" : "false")});
    Generator g(generator_options(c, camera, false));
    import_state_dict(s.dir / "sd.pt", g);
    g->eval();
    auto load = [](const std::filesystem::path& p) {
      std::ifstream f(p, std::ios::binary);
      std::vector<char> b((std::istreambuf_iterator<char>(f)), {});
      return torch::pickle_load(b).toTensor();
    };
    torch::NoGradGuard ng;
    const auto out = g->forward(load(s.dir / "in.pt"));
    CHECK((out - load(s.dir / "out.pt")).abs().max().item<double>() < 1e-4);

    // C++ exports weights, input and output; Python checks them.
    {
      torch::NoGradGuard ng2;
      for (auto& p : g->parameters()) p.add_(torch::randn(p.sizes()) * 0.01);
    }
    const auto Y = torch::randn({2, 4, 500, 620}) * 0.05;
    const auto mine = g->forward(Y);
    export_state_dict(s.dir / "sd2.pt", g);
    auto save = [](const std::filesystem::path& p, const torch::Tensor& t) {
      const auto b = torch::pickle_save(t);
      std::ofstream(p, std::ios::binary).write(b.data(), b.size());
    };
    save(s.dir / "in2.pt", Y);
    save(s.dir / "out2.pt", mine);
    cmd = "/usr/bin/python3 '" + script.string() + "' check '" + (s.dir / "sd2.pt").string() + "' '" +
          (s.dir / "in2.pt").string() + "' '" + (s.dir / "out2.pt").string() + "' 4 " + ks;
    CHECK(std::system(cmd.c_str()) == 0);
  }
}

TEST_CASE("at paper width, the exported state dict loads into FlatNet-sep with strict=True", "[nn][python][slow]") {
  if (!test::python_has_torch()) SKIP_TEST("/usr/bin/python3 has no torch");
  test::Scratch s("paper_sd");
  const auto script = test::source_dir() / "scripts" / "flatnet_reference.py";
  for (const char* shared : {"true", "false"}) {
    INFO("model.inversion.shared=" << shared);
    const auto config = Config::load({}, {"model.unet.width=128", std::string("model.inversion.shared=") + shared});
    Generator g(generator_options(config, CameraConfig{}, false));  // 500x620 -> 256x256, 128 filters
    for (auto layout : {StateDictLayout::state_dict, StateDictLayout::flatnet_checkpoint}) {
      const auto file = s.dir / "paper.pt";
      std::filesystem::remove(file);
      export_state_dict(file, g, layout);
      const std::string loader = layout == StateDictLayout::state_dict ? " load " : " load_checkpoint ";
      const auto r = test::run_shell("/usr/bin/python3 " + test::q(script) + loader + test::q(file) + " 128 " +
                                     (std::string(shared) == "true" ? "1" : "4"));
      INFO(r.output);
      CHECK(r.code == 0);
      CHECK_THAT(r.output, Contains("strict=True"));
    }
  }
}

TEST_CASE("inference levers (BN folding, channels-last, GEMM upsampling) keep the generator's output", "[nn][levers]") {
  torch::manual_seed(3);
  auto o = tiny_options();
  o.unet.width = 4;
  Generator plain(o);
  {  // non-trivial batch-norm statistics, so folding has something to fold
    torch::NoGradGuard no_grad;
    for (auto& b : plain->named_buffers())
      if (b.key().find("running_var") != std::string::npos)
        b.value().uniform_(0.5, 1.5);
      else if (b.key().find("running_mean") != std::string::npos)
        b.value().uniform_(-0.2, 0.2);
    for (auto& p : plain->named_parameters())
      if (p.key().find("conv.1.weight") != std::string::npos) p.value().uniform_(0.5, 1.5);
  }
  plain->eval();
  const auto Y = torch::randn({2, 4, o.rows, o.cols}) * 0.1;
  torch::Tensor expected;
  {
    torch::NoGradGuard no_grad;
    expected = plain->forward(Y);
  }
  auto of = o;
  of.inversion.phil = o.inversion.phil.clone(), of.inversion.phir = o.inversion.phir.clone();
  auto fast = Generator(of);
  {
    torch::NoGradGuard no_grad;
    for (auto& p : fast->named_parameters()) p.value().copy_(plain->named_parameters()[p.key()]);
    for (auto& b : fast->named_buffers()) b.value().copy_(plain->named_buffers()[b.key()]);
  }
  fast->prepare_inference(parse_inference_levers("fold,channels-last,gemm-up,onednn"));
  torch::NoGradGuard no_grad;
  const auto got = fast->forward(Y);
  CHECK(got.sizes() == expected.sizes());
  CHECK((got - expected).abs().max().item<double>() < 1e-5);
  CHECK_THROWS_WITH(parse_inference_levers("fold,turbo"), Contains("turbo"));
}

TEST_CASE("training levers (channels-last, GEMM upsampling) give the same loss and gradients", "[nn][levers]") {
  torch::manual_seed(4);
  auto o = tiny_options();
  o.unet.width = 4;
  auto ob = o;
  ob.inversion.phil = o.inversion.phil.clone(), ob.inversion.phir = o.inversion.phir.clone();
  Generator a(o), b(ob);
  {
    torch::NoGradGuard no_grad;
    for (auto& p : b->named_parameters()) p.value().copy_(a->named_parameters()[p.key()]);
  }
  b->prepare_training(InferenceLevers{});
  const auto Y = torch::randn({2, 4, o.rows, o.cols}) * 0.1;
  const auto target = torch::rand({2, 3, o.scene, o.scene});
  // Training mode: the same loss (batch norm on this tiny net's 1x1 deepest level amplifies
  // rounding in the gradients, so those are compared in eval mode below).
  const double la = torch::mse_loss(a->forward(Y), target).item<double>();
  const double lb = torch::mse_loss(b->forward(Y), target).item<double>();
  CHECK(std::abs(la - lb) <= 1e-5 * la);
  a->eval(), b->eval();
  torch::mse_loss(a->forward(Y), target).backward();
  torch::mse_loss(b->forward(Y), target).backward();
  for (const auto& p : a->named_parameters()) {
    INFO(p.key());
    const auto ga = p.value().grad(), gb = b->named_parameters()[p.key()].grad();
    REQUIRE(gb.defined());
    CHECK((ga - gb).abs().max().item<double>() <= 1e-4 * ga.abs().max().item<double>() + 1e-7);
  }
}

TEST_CASE("perceptual loss: channels-last VGG gives the same loss, bf16 autocast agrees, gradients reach the image",
          "[nn][loss][bf16]") {
  torch::manual_seed(12);
  Vgg16Features vgg;
  {
    torch::NoGradGuard no_grad;
    for (auto& p : vgg->parameters()) p.mul_(3.0);  // default init fades with depth; keep relu4_3 alive
  }
  const auto y = torch::rand({2, 3, 32, 32});
  auto loss_and_grad = [&](bool bf16) {
    const auto x = (y + 0.2 * torch::randn_like(y)).clamp(0, 1).requires_grad_(true);
    const auto loss = perceptual_loss(vgg, x, y, bf16);
    loss.backward();
    REQUIRE(x.grad().defined());
    return std::make_pair(loss.item<double>(), x.grad().clone());
  };
  torch::manual_seed(1);
  const auto [fp32, g32] = loss_and_grad(false);
  weights_to_channels_last(*vgg);
  CHECK(vgg->parameters()[0].is_contiguous(at::MemoryFormat::ChannelsLast));
  torch::manual_seed(1);
  const auto [cl, gcl] = loss_and_grad(false);
  torch::manual_seed(1);
  const auto [bf16, gbf] = loss_and_grad(true);
  CHECK(fp32 > 0);
  CHECK(cl == Approx(fp32).epsilon(1e-4));
  CHECK(bf16 == Approx(fp32).epsilon(0.03));  // bf16 keeps 8 bits of mantissa
  CHECK((gcl - g32).abs().max().item<double>() <= 1e-4 * g32.abs().max().item<double>());
  const double cosine = (gbf * g32).sum().item<double>() / (gbf.norm() * g32.norm()).item<double>();
  CHECK(cosine > 0.97);  // measured 0.984: bf16 rounding through ten convolutions, as Python autocast
  for (const auto& p : vgg->parameters()) CHECK_FALSE(p.grad().defined());  // frozen
}

TEST_CASE("SSIM loss is 1 - the reported SSIM, differentiable, and 0 on identical images", "[nn][loss]") {
  torch::manual_seed(8);
  const auto y = torch::rand({2, 3, 24, 24});
  const auto x = (y + 0.1 * torch::randn({2, 3, 24, 24})).clamp(0, 1).requires_grad_(true);
  const auto loss = ssim_loss(x, y);
  const double reported = 0.5 * (ssim(x[0].detach(), y[0]) + ssim(x[1].detach(), y[1]));
  CHECK(loss.item<double>() == Approx(1.0 - reported).epsilon(1e-4));
  CHECK(ssim_loss(y, y).item<double>() == Approx(0.0).margin(1e-6));
  loss.backward();
  REQUIRE(x.grad().defined());
  CHECK(x.grad().abs().sum().item<double>() > 0);
  CHECK_THROWS_WITH(ssim_loss(torch::rand({1, 3, 8, 8}), torch::rand({1, 3, 8, 8})), Contains("11x11"));
}

TEST_CASE("CIELAB conversion matches skimage.color.rgb2lab (D65)", "[nn][loss]") {
  const auto rgb = torch::tensor({1.0f, 0.0f, 0.2f, 0.01f, 0.0f, 1.0f, 0.5f, 0.01f, 0.0f, 0.0f, 0.7f, 0.01f})
                       .view({1, 3, 1, 4});                 // red, green, a blue-grey, near black
  const auto lab = srgb_to_lab(rgb).squeeze(0).squeeze(1);  // {3,4}
  const std::vector<std::array<double, 3>> expected = {{53.2405879, 80.0923082, 67.2027510},
                                                       {87.7350995, -86.1830297, 83.1797032},
                                                       {50.9720364, -6.39817671, -33.7093230},
                                                       {0.699142415, -4.43881748e-05, 8.41378036e-05}};
  for (int i = 0; i < 4; ++i)
    for (int c = 0; c < 3; ++c) CHECK(lab[c][i].item<double>() == Approx(expected[i][c]).margin(2e-3));
}

TEST_CASE("the weight-free perceptual terms: 0 on the truth, positive otherwise, gradients reach the output",
          "[nn][loss]") {
  torch::manual_seed(9);
  const auto y = torch::rand({2, 3, 32, 32});
  Discriminator d(DiscriminatorOptions{"thesis", 8});
  for (auto& p : d->parameters()) p.set_requires_grad(false);  // as the generator step does
  const std::vector<std::pair<std::string, std::function<torch::Tensor(const torch::Tensor&)>>> terms = {
      {"feature matching", [&](const torch::Tensor& x) { return feature_matching_loss(d, x, y); }},
      {"focal frequency", [&](const torch::Tensor& x) { return focal_frequency_loss(x, y); }},
      {"chroma", [&](const torch::Tensor& x) { return chroma_loss(x, y); }},
      {"gradient", [&](const torch::Tensor& x) { return gradient_loss(x, y); }},
      {"detail energy", [&](const torch::Tensor& x) { return detail_energy_loss(x, y); }},
      {"random features", [&](const torch::Tensor& x) { return random_feature_loss(x, y); }}};
  d->eval();  // batch norm on running statistics: features of y are the same whichever batch holds it
  for (const auto& [name, term] : terms) {
    INFO(name);
    CHECK(term(y).item<double>() == Approx(0.0).margin(1e-7));
    const auto x = (y + 0.1 * torch::randn_like(y)).clamp(0, 1).requires_grad_(true);
    const auto loss = term(x);
    CHECK(loss.item<double>() > 1e-4);
    loss.backward();
    REQUIRE(x.grad().defined());
    CHECK(torch::isfinite(x.grad()).all().item<bool>());
    CHECK(x.grad().abs().sum().item<double>() > 0);
  }
  for (const auto& p : d->parameters()) CHECK_FALSE(p.grad().defined());
}

TEST_CASE(
    "the terms see what they are for: chroma ignores a luma change, gradient a constant offset, frequency "
    "a blur",
    "[nn][loss]") {
  torch::manual_seed(10);
  // A photograph (a blur of white noise would remove almost all of its edges at any size).
  const auto y = read_rgb(test::data_dir() / "golden" / "inet_n02980441_castle_scene.png").unsqueeze(0);
  const auto grey = y.mean(1, true).repeat({1, 3, 1, 1});  // same luma-ish, no colour
  CHECK(chroma_loss(grey, y).item<double>() > 0.02);       // colour lost costs
  CHECK(chroma_loss(y, grey).item<double>() > 0.02);
  // A uniform offset moves no edge: the gradient term is 0, MSE is not.
  const auto dimmer = y * 0.8 + 0.1;
  CHECK(gradient_loss(y * 0.8 + (0.1 + 0.05), dimmer).item<double>() == Approx(0.0).margin(1e-6));
  // A blur loses high frequencies: the focal term grows with the blur.
  namespace F = torch::nn::functional;
  const auto blur3 = F::avg_pool2d(y, F::AvgPool2dFuncOptions(3).stride(1).padding(1).count_include_pad(false));
  const auto blur5 = F::avg_pool2d(y, F::AvgPool2dFuncOptions(5).stride(1).padding(2).count_include_pad(false));
  CHECK(focal_frequency_loss(blur5, y).item<double>() > focal_frequency_loss(blur3, y).item<double>());
  CHECK(gradient_loss(blur5, y).item<double>() > gradient_loss(blur3, y).item<double>());
}

TEST_CASE("the detail term wants the truth's texture, not its phase, and the random features are fixed and see blur",
          "[nn][loss]") {
  const auto y = read_rgb(test::data_dir() / "golden" / "inet_n02980441_castle_scene.png").unsqueeze(0);
  namespace F = torch::nn::functional;
  auto box = [&](int k) {
    return F::avg_pool2d(y, F::AvgPool2dFuncOptions(k).stride(1).padding(k / 2).count_include_pad(false));
  };
  const auto blur3 = box(3), blur5 = box(5);
  // The same texture two pixels over: a large pixel error, but each 8x8 window holds as much detail.
  const auto shifted = torch::roll(y, {2, 2}, {2, 3});
  const double mse_shift = torch::mse_loss(shifted, y).item<double>(),
               mse_blur = torch::mse_loss(blur3, y).item<double>();
  REQUIRE(mse_shift > mse_blur);
  CHECK(detail_energy_loss(shifted, y).item<double>() < 0.5 * detail_energy_loss(blur3, y).item<double>());
  CHECK(detail_energy_loss(blur5, y).item<double>() > detail_energy_loss(blur3, y).item<double>());
  // A step down its gradient sharpens a blurred picture: eval's detail measure rises.
  const auto x = blur5.clone().requires_grad_(true);
  detail_energy_loss(x, y).backward();
  const auto stepped = (blur5 - 0.05 * x.grad() / x.grad().abs().max()).clamp(0, 1);  // at most 0.05 a pixel
  CHECK(luma_detail(stepped[0]) > luma_detail(blur5[0]) * 1.02);
  CHECK(detail_energy_loss(stepped, y).item<double>() < detail_energy_loss(blur5, y).item<double>());
  // The random network: fixed weights (one seed), VGG-like stage shapes, and a blur costs more the larger it is.
  const auto small = y.slice(2, 0, 64).slice(3, 0, 64);
  const auto f1 = random_features(small), f2 = random_features(small);
  REQUIRE(f1.size() == 3);
  CHECK(f1[0].sizes() == torch::IntArrayRef({1, 16, 64, 64}));
  CHECK(f1[1].sizes() == torch::IntArrayRef({1, 32, 32, 32}));
  CHECK(f1[2].sizes() == torch::IntArrayRef({1, 64, 16, 16}));
  for (size_t i = 0; i < f1.size(); ++i) CHECK(torch::equal(f1[i], f2[i]));
  CHECK(random_feature_loss(blur5, y).item<double>() > random_feature_loss(blur3, y).item<double>());
  CHECK_THROWS(detail_energy_loss(y.slice(2, 0, 16), y.slice(2, 0, 16)));  // too small for three bands
}

TEST_CASE("the stripe term is eval's stripe energy (squared, over 255^2), ignores an offset, and has a gradient",
          "[nn][loss]") {
  const auto y = read_rgb(test::data_dir() / "golden" / "inet_n02980441_castle_scene.png").unsqueeze(0);  // {1,3,H,W}
  // Rows 4 codes brighter every fourth row: a periodic stripe the trend does not follow.
  const auto rows = (torch::arange(y.size(2)) % 4 == 0).to(torch::kFloat32).view({1, 1, -1, 1});
  const auto striped = y + 4.0 / 255 * rows;
  const double energy = stripe_energy(striped[0], y[0]);
  REQUIRE(energy > 1.0);
  CHECK(255 * std::sqrt(stripe_loss(striped, y).item<double>()) == Approx(energy).epsilon(1e-4));
  CHECK(stripe_loss(y + 0.05, y).item<double>() == Approx(0.0).margin(1e-10));  // no stripe in an offset
  // A batch is the mean of its images (equal sizes).
  const auto pair = stripe_loss(torch::cat({striped, y}), torch::cat({y, y})).item<double>();
  CHECK(pair == Approx(stripe_loss(striped, y).item<double>() / 2).epsilon(1e-5));
  const auto x = striped.clone().requires_grad_(true);
  stripe_loss(x, y).backward();
  REQUIRE(x.grad().defined());
  CHECK(torch::isfinite(x.grad()).all().item<bool>());
  // Descending the gradient lowers the stripes.
  CHECK(stripe_loss(striped - 1e4 * x.grad(), y).item<double>() < stripe_loss(striped, y).item<double>());
}

TEST_CASE("scripts/stripe_split.py reproduces eval's stripe energy and splits it into rows and columns",
          "[nn][loss][python][solo]") {
  if (std::system("/usr/bin/python3 -c 'import numpy, PIL' >/dev/null 2>&1") != 0)
    SKIP_TEST("/usr/bin/python3 has no numpy or Pillow");
  test::Scratch s("stripe_split");
  const auto y = read_rgb(test::data_dir() / "golden" / "inet_n02980441_castle_scene.png");  // {3,H,W}
  const auto rows = (torch::arange(y.size(1)) % 4 == 0).to(torch::kFloat32).view({1, -1, 1});
  // One picture striped along its rows only, one along its columns only (8 codes, every fourth).
  const auto by_rows = (y + 8.0 / 255 * rows).clamp(0, 1),
             by_cols = (y + 8.0 / 255 * rows.view({1, 1, -1})).clamp(0, 1);
  std::filesystem::create_directories(s.dir / "gt");
  std::filesystem::create_directories(s.dir / "set" / "rows");
  std::filesystem::create_directories(s.dir / "set" / "cols");
  write_rgb8(s.dir / "gt" / "a.png", y);
  write_rgb8(s.dir / "set" / "rows" / "a.png", by_rows);
  write_rgb8(s.dir / "set" / "cols" / "a.png", by_cols);
  const auto script = test::source_dir() / "scripts" / "stripe_split.py";
  const auto r = test::run_shell("/usr/bin/python3 " + test::q(script) + " " + test::q(s.dir / "set") + " " +
                                 test::q(s.dir / "gt") + " rows cols");
  REQUIRE(r.code == 0);
  // method stripes fixed rows border inside cols border inside
  std::istringstream lines(r.output);
  std::string header, name;
  std::getline(lines, header);
  std::map<std::string, std::vector<double>> got;
  for (int i = 0; i < 2 && lines >> name; ++i) {
    auto& v = got[name];
    for (double x; v.size() < 8 && lines >> x;) v.push_back(x);
  }
  REQUIRE(got["rows"].size() == 8);
  REQUIRE(got["cols"].size() == 8);
  // Eval's stripe energy of the files as written (8-bit), to the script's 3 decimals.
  CHECK(got["rows"][0] == Approx(stripe_energy(read_rgb(s.dir / "set" / "rows" / "a.png"), y)).margin(1e-3));
  CHECK(got["cols"][0] == Approx(stripe_energy(read_rgb(s.dir / "set" / "cols" / "a.png"), y)).margin(1e-3));
  CHECK(got["rows"][1] == Approx(got["rows"][0]).margin(1e-3));  // one picture: all of it is the fixed pattern
  // Row stripes land in the row profile, column stripes in the column profile; border + inside = total.
  CHECK(got["rows"][2] > 20 * got["rows"][5]);
  CHECK(got["cols"][5] > 20 * got["cols"][2]);
  CHECK(got["rows"][3] + got["rows"][4] == Approx(got["rows"][2]).margin(1.0));
  // A missing truth is named.
  std::filesystem::remove(s.dir / "gt" / "a.png");
  const auto bad = test::run_shell("/usr/bin/python3 " + test::q(script) + " " + test::q(s.dir / "set") + " " +
                                   test::q(s.dir / "gt") + " rows");
  CHECK(bad.code != 0);
  CHECK_THAT(bad.output, Catch::Matchers::Contains("a.png missing"));
}

TEST_CASE("the PSNR term is minus eval's mean PSNR, counts every image in decibels, and has a gradient", "[nn][loss]") {
  const auto y = read_rgb(test::data_dir() / "golden" / "inet_n02980441_castle_scene.png").unsqueeze(0);  // {1,3,H,W}
  const auto dim = 0.2 * y;                                                                               // a dim scene
  torch::manual_seed(3);
  const auto error = 0.02 * torch::randn_like(y);
  const auto x = torch::cat({(y + error).clamp(0, 1), (dim + 0.2 * error).clamp(0, 1)});  // {2,3,H,W}
  const auto truth = torch::cat({y, dim});
  const double expected = -(psnr(x[0], truth[0]) + psnr(x[1], truth[1])) / 2;
  CHECK(psnr_loss(x, truth).item<double>() == Approx(expected).epsilon(1e-4));
  // Halving either image's error gains the same 3.01 dB / 2, bright or dim: the pooled MSE would
  // gain 25 times less from the dim one.
  const auto halve = [&](int64_t i) {
    auto h = x.clone();
    h[i] = truth[i] + 0.5 * (x[i] - truth[i]);
    return psnr_loss(x, truth).item<double>() - psnr_loss(h, truth).item<double>();
  };
  CHECK(halve(0) == Approx(10 * std::log10(4.0) / 2).epsilon(1e-4));
  CHECK(halve(1) == Approx(10 * std::log10(4.0) / 2).epsilon(1e-4));
  CHECK(std::isfinite(psnr_loss(truth, truth).item<double>()));  // an exact reconstruction: -100 dB, not -inf
  const auto leaf = x.clone().requires_grad_(true);
  psnr_loss(leaf, truth).backward();
  REQUIRE(leaf.grad().defined());
  CHECK(torch::isfinite(leaf.grad()).all().item<bool>());
  // The dim image's gradient is the larger: its error is 5 times smaller, its pull 5 times stronger.
  CHECK(leaf.grad()[1].norm().item<double>() > 4 * leaf.grad()[0].norm().item<double>());
  CHECK_THROWS(psnr_loss(x, truth.slice(3, 1)));
}

TEST_CASE("batch norm and its activation (ReLU, swish) by oneDNN: LibTorch's values, gradients and running statistics",
          "[nn][onednn]") {
  torch::manual_seed(13);
  for (const auto activation : {NormActivation::relu, NormActivation::swish})
    for (const auto type : {torch::kFloat32, torch::kBFloat16}) {
      const bool relu = activation == NormActivation::relu;
      INFO((relu ? "relu " : "swish ") << type);
      const auto cl = at::MemoryFormat::ChannelsLast;
      const auto x0 = (torch::randn({3, 5, 6, 7}) * 2 + 0.5).to(type).contiguous(cl);
      if (!onednn_batch_norm_runs(x0, 1e-5, activation)) {
        CHECK(type == torch::kBFloat16);  // fp32 runs on every CPU oneDNN supports
        continue;
      }
      torch::nn::BatchNorm2d reference(torch::nn::BatchNormOptions(5).momentum(0.3));
      {
        torch::NoGradGuard no_grad;
        reference->weight.uniform_(0.5, 1.5);
        reference->bias.uniform_(-0.5, 0.5);
      }
      auto weight = reference->weight.detach().clone().requires_grad_();
      auto bias = reference->bias.detach().clone().requires_grad_();
      auto running_mean = torch::zeros({5}), running_var = torch::ones({5});
      auto x1 = x0.clone().requires_grad_(), x2 = x0.clone().requires_grad_();
      const auto mine =
          onednn_batch_norm_activation(x1, weight, bias, running_mean, running_var, 0.3, 1e-5, activation);
      const auto normed = reference->forward(x2);  // LibTorch's batch norm in bf16 keeps bf16
      const auto expected = relu ? torch::relu(normed) : normed * torch::sigmoid(normed);
      REQUIRE(mine.sizes() == expected.sizes());
      CHECK(mine.scalar_type() == type);
      CHECK(mine.is_contiguous(cl));
      const double tol = type == torch::kFloat32 ? 1e-4 : 3e-2;
      CHECK(torch::allclose(mine.to(torch::kFloat32), expected.to(torch::kFloat32), tol, tol));
      if (relu)
        CHECK((mine == 0).sum().item<int64_t>() > 0);  // the ReLU is there
      else
        CHECK((mine < -0.05).sum().item<int64_t>() > 0);  // swish dips below zero (to -0.278)
      CHECK(torch::allclose(running_mean, reference->running_mean, 1e-4, 1e-5));
      CHECK(torch::allclose(running_var, reference->running_var, 1e-4, 1e-5));
      const auto weights = torch::randn(mine.sizes()).to(type);
      (mine.to(torch::kFloat32) * weights.to(torch::kFloat32)).sum().backward();
      (expected.to(torch::kFloat32) * weights.to(torch::kFloat32)).sum().backward();
      CHECK(torch::allclose(x1.grad().to(torch::kFloat32), x2.grad().to(torch::kFloat32), tol, tol));
      CHECK(torch::allclose(weight.grad(), reference->weight.grad(), 10 * tol, tol));
      CHECK(torch::allclose(bias.grad(), reference->bias.grad(), 10 * tol, tol));
    }
  CHECK_FALSE(onednn_batch_norm_runs(torch::randn({2, 3, 4, 4})));  // channels-first: LibTorch's path
  CHECK_FALSE(onednn_batch_norm_runs(torch::randn({1, 3, 1, 1}).contiguous(at::MemoryFormat::ChannelsLast)));
}

TEST_CASE("a module's batch norm and swish: oneDNN in training counts its batches, LibTorch's in eval, same values",
          "[nn][onednn]") {
  torch::manual_seed(14);
  const auto x = torch::randn({2, 4, 5, 5}).contiguous(at::MemoryFormat::ChannelsLast);
  torch::nn::BatchNorm2d bn(4), reference(4);
  const auto swish = [](const torch::Tensor& z) { return z * torch::sigmoid(z); };
  const auto trained = batch_norm_activation(*bn, x, NormActivation::swish);
  CHECK(torch::allclose(trained, swish(reference->forward(x)), 1e-4, 1e-5));
  CHECK(bn->num_batches_tracked.item<int64_t>() == 1);
  CHECK(torch::allclose(bn->running_var, reference->running_var, 1e-4, 1e-6));
  bn->eval(), reference->eval();
  const auto evaluated = batch_norm_activation(*bn, x, NormActivation::swish);  // running statistics
  CHECK(torch::allclose(evaluated, swish(reference->forward(x)), 1e-4, 1e-5));
  CHECK(bn->num_batches_tracked.item<int64_t>() == 1);
}

TEST_CASE("a training convolution by oneDNN: LibTorch's values and gradients (stride, padding, bias, layouts, types)",
          "[nn][onednn]") {
  torch::manual_seed(16);
  const auto cl = at::MemoryFormat::ChannelsLast;
  struct Case {
    int64_t kernel, stride, padding;
    bool bias, weight_channels_last;
  };
  // The U-Net's 3x3 convolutions, the discriminator's stride-2 ones and its 1x1 head with padding 1.
  for (const auto c :
       {Case{3, 1, 1, false, true}, Case{3, 2, 1, true, true}, Case{1, 1, 1, true, false}, Case{3, 1, 1, true, false}})
    for (const auto type : {torch::kFloat32, torch::kBFloat16}) {
      INFO("kernel " << c.kernel << " stride " << c.stride << " bias " << c.bias << " " << type);
      const auto x0 = torch::randn({2, 5, 9, 11}).to(type).contiguous(cl);
      auto w0 = torch::randn({7, 5, c.kernel, c.kernel}) * 0.3;
      if (c.weight_channels_last) w0 = w0.contiguous(cl);
      const auto b0 = c.bias ? torch::randn({7}) : torch::Tensor();
      if (!onednn_conv2d_runs(x0, w0, b0, c.stride, c.padding)) {
        CHECK(type == torch::kBFloat16);  // fp32 runs on every CPU oneDNN supports
        continue;
      }
      auto x1 = x0.clone().requires_grad_(), x2 = x0.to(torch::kFloat32).requires_grad_();
      auto w1 = w0.clone().requires_grad_(), w2 = w0.clone().requires_grad_();
      auto b1 = c.bias ? b0.clone().requires_grad_() : b0, b2 = c.bias ? b0.clone().requires_grad_() : b0;
      const auto work_before = onednn_flops();
      const auto mine = onednn_conv2d(x1, w1, b1, c.stride, c.padding);
      // The reference in fp32 from the same (rounded) input: bf16 differs by its output's rounding.
      const auto expected = torch::conv2d(x2, w2, b2, c.stride, c.padding);
      REQUIRE(mine.sizes() == expected.sizes());
      CHECK(mine.scalar_type() == type);
      CHECK(mine.is_contiguous(cl));
      const double tol = type == torch::kFloat32 ? 1e-4 : 3e-2;
      CHECK(torch::allclose(mine.to(torch::kFloat32), expected, tol, tol));
      const auto weights = torch::randn(expected.sizes());
      (mine.to(torch::kFloat32) * weights).sum().backward();
      (expected * weights).sum().backward();
      CHECK(torch::allclose(x1.grad().to(torch::kFloat32), x2.grad(), tol, tol));
      CHECK(torch::allclose(w1.grad(), w2.grad(), tol, 10 * tol));
      CHECK(w1.grad().scalar_type() == torch::kFloat32);
      CHECK(w1.grad().is_contiguous(c.weight_channels_last ? cl : at::MemoryFormat::Contiguous));  // the weight's
      if (c.bias) CHECK(torch::allclose(b1.grad(), b2.grad(), tol, 10 * tol));
      // Counted: the forward and both gradients, each 2 B O H' W' I k k.
      const double pass = 2.0 * expected.numel() * 5 * c.kernel * c.kernel;
      CHECK(static_cast<double>(onednn_flops() - work_before) == Approx(3 * pass));
    }
  const auto x = torch::randn({2, 5, 9, 11}).contiguous(cl);
  CHECK_FALSE(onednn_conv2d_runs(x.contiguous(), torch::randn({7, 5, 3, 3}), {}, 1, 1));  // channels-first
  CHECK_FALSE(onednn_conv2d_runs(x, torch::randn({7, 4, 3, 3}), {}, 1, 1));               // channels disagree
  CHECK_FALSE(onednn_conv2d_runs(x, torch::randn({7, 5, 3, 3}).to(torch::kFloat64), {}, 1, 1));
  CHECK_THROWS_WITH(onednn_conv2d(x.contiguous(), torch::randn({7, 5, 3, 3}), {}, 1, 1),
                    Catch::Matchers::Contains("channels-last"));
}

TEST_CASE("a module's convolution: oneDNN's in fp32 where a gradient is wanted, LibTorch's elsewhere (autocast too)",
          "[nn][onednn]") {
  torch::manual_seed(17);
  const auto cl = at::MemoryFormat::ChannelsLast;
  torch::nn::Conv2d conv(torch::nn::Conv2dOptions(4, 6, 3).stride(2).padding(1));
  const auto x = torch::randn({2, 4, 10, 10}).contiguous(cl);
  auto work = onednn_flops();
  const auto trained = convolve(*conv, x);  // the weight wants a gradient
  CHECK(onednn_flops() > work);
  CHECK(torch::allclose(trained, conv->forward(x), 1e-4, 1e-5));
  trained.sum().backward();  // the weight's gradient only: x wants none
  REQUIRE(conv->weight.grad().defined());
  CHECK(onednn_flops() - work == 2 * static_cast<uint64_t>(2 * trained.numel() * 4 * 9));
  work = onednn_flops();
  {
    torch::NoGradGuard no_grad;
    CHECK(torch::allclose(convolve(*conv, x), conv->forward(x), 1e-4, 1e-5));
  }
  convolve(*conv, x.contiguous());  // channels-first: LibTorch's
  CHECK(onednn_flops() == work);
  if (resolve_precision("auto") == Precision::bf16) {  // LibTorch's bf16 convolutions need AVX-512
    AutocastGuard autocast(true);
    CHECK(convolve(*conv, x).scalar_type() == torch::kBFloat16);  // LibTorch's, in autocast's type
    CHECK(onednn_flops() == work);
  }
}

TEST_CASE("the discriminator with channels-last weights: the same logits and gradients as with plain ones", "[nn]") {
  torch::manual_seed(15);
  Discriminator plain(DiscriminatorOptions{"thesis", 8});
  Discriminator nhwc(DiscriminatorOptions{"thesis", 8});
  {
    torch::NoGradGuard no_grad;
    const auto from = plain->parameters(), to = nhwc->parameters();
    for (size_t i = 0; i < from.size(); ++i) to[i].copy_(from[i]);
  }
  weights_to_channels_last(*nhwc);
  REQUIRE(nhwc->parameters()[0].is_contiguous(at::MemoryFormat::ChannelsLast));
  const auto image = torch::rand({2, 3, 32, 32});  // NCHW, as the loader gives the truth
  auto a = image.clone().requires_grad_(), b = image.clone().requires_grad_();
  const auto la = plain->forward(a), lb = nhwc->forward(b);
  CHECK(torch::allclose(la, lb, 1e-4, 1e-5));
  la.sum().backward();
  lb.sum().backward();
  CHECK(torch::allclose(a.grad(), b.grad(), 1e-4, 1e-6));
  const auto ga = plain->parameters()[0].grad(), gb = nhwc->parameters()[0].grad();
  CHECK(torch::allclose(ga, gb, 1e-4, 1e-6));
}

TEST_CASE("the first stage is FlatNet's leaky_relu(W1^T Y W2), values and gradients, per channel or shared", "[nn]") {
  torch::manual_seed(12);
  for (const int64_t k : {4, 1}) {
    INFO("k = " << k);
    const auto o = tiny_options(k);
    FlatInversion inv(o.inversion);
    const auto Y0 = torch::randn({3, 4, o.rows, o.cols});
    auto Y1 = Y0.clone().requires_grad_(), Y2 = Y0.clone().requires_grad_();
    const auto L = inv->PhiL.detach().clone().requires_grad_(), R = inv->PhiR.detach().clone().requires_grad_();
    // The reference: torch::matmul over {B,4,...} with the weights as {k,rows,N}, {k,cols,N}.
    const auto X = torch::matmul(L.permute({2, 0, 1}).transpose(1, 2), torch::matmul(Y2, R.permute({2, 0, 1})));
    const auto reference = torch::leaky_relu(X, 0.01).flip({1});
    const auto mine = inv->forward(Y1);
    REQUIRE(mine.sizes() == reference.sizes());
    CHECK(torch::allclose(mine, reference, 1e-4, 1e-5));
    const auto weights = torch::randn_like(reference);
    (mine * weights).sum().backward();
    (reference * weights).sum().backward();
    CHECK(torch::allclose(Y1.grad(), Y2.grad(), 1e-4, 1e-5));
    CHECK(torch::allclose(inv->PhiL.grad(), L.grad(), 1e-4, 1e-5));
    CHECK(torch::allclose(inv->PhiR.grad(), R.grad(), 1e-4, 1e-5));
  }
}

TEST_CASE("inversion crops equal the matching window of the whole first stage", "[nn]") {
  torch::manual_seed(9);
  const auto o = tiny_options(4);
  FlatInversion inv(o.inversion);
  const auto Y = torch::randn({2, 4, o.rows, o.cols});
  torch::NoGradGuard no_grad;
  const auto full = inv->forward(Y);  // {2,4,16,16}
  const std::vector<std::pair<int64_t, int64_t>> corners{{0, 8}, {5, 3}};
  const auto crops = inv->forward_crops(Y, corners, 8);
  REQUIRE(crops.sizes() == torch::IntArrayRef({2, 4, 8, 8}));
  CHECK(torch::allclose(crops[0], full[0].slice(1, 0, 8).slice(2, 8, 16), 1e-5, 1e-6));
  CHECK(torch::allclose(crops[1], full[1].slice(1, 5, 13).slice(2, 3, 11), 1e-5, 1e-6));
  Generator g(tiny_options());
  CHECK_THROWS_WITH(g->forward_crops(Y, {{10, 0}, {0, 0}}, 16), Contains("leaves"));
  CHECK_THROWS_WITH(g->forward_crops(Y, {{0, 0}, {0, 0}}, 12), Contains("multiple of 16"));
}

TEST_CASE("bf16 autocast: the enhancer runs in bf16, weights and gradients stay fp32, output close to fp32",
          "[nn][bf16]") {
  torch::manual_seed(10);
  auto o = tiny_options();
  o.unet.width = 4;
  Generator g(o);
  g->eval();
  const auto Y = torch::randn({2, 4, o.rows, o.cols}) * 0.1;
  const auto fp32 = g->forward(Y);
  g->set_autocast_bf16(true);
  const auto bf16 = g->forward(Y);
  CHECK(bf16.scalar_type() == torch::kFloat32);  // the sigmoid and the losses see fp32
  CHECK((bf16 - fp32).abs().max().item<double>() < 0.03);
  CHECK((bf16 - fp32).abs().max().item<double>() > 0);  // it did run in bf16
  torch::mse_loss(bf16, torch::rand_like(bf16)).backward();
  for (const auto& p : g->named_parameters()) {
    INFO(p.key());
    CHECK(p.value().scalar_type() == torch::kFloat32);
    REQUIRE(p.value().grad().defined());
    CHECK(p.value().grad().scalar_type() == torch::kFloat32);
  }
  CHECK_FALSE(at::autocast::is_cpu_enabled());  // the guard restored the thread's state
}

TEST_CASE("every setting of the defaults files is documented on its line", "[config]") {
  const auto configs = test::source_dir() / "configs";
  for (const char* file : {"defaults.yaml", "mask_defaults.yaml", "separable_defaults.yaml"}) {
    const auto settings = describe_settings(configs / file);
    CHECK(settings.size() == Config::load({}, {}, configs / file).values().size());
    for (const auto& s : settings) {
      INFO(file << ": " << s.key << " has no comment on its line (what `flatnet options` shows)");
      CHECK(s.doc.size() >= 3);
    }
  }
  // A range comes from config.cpp's table; the comment's continuation lines are joined.
  const auto train = describe_settings(configs / "defaults.yaml");
  const auto find = [&](const std::string& key) {
    return *std::find_if(train.begin(), train.end(), [&](const SettingDoc& s) { return s.key == key; });
  };
  CHECK(find("train.batch").range == "1 to 4096 samples");
  CHECK(find("train.precision").range.empty());
  CHECK_THAT(find("train.crop").doc, Contains("multiple of 16") && Contains("validation is at full size"));
}

TEST_CASE("setting comments: sections, continuation lines, quotes and a '#' inside a value", "[config]") {
  test::Scratch s("setting_docs");
  const auto file = s.dir / "d.yaml";
  std::ofstream(file) << "# a header comment\n"
                         "a:                # a section's own comment is no setting's\n"
                         "  b: 1            # the b\n"
                         "                  # and more of it\n"
                         "  # a comment line of the section, not b's\n"
                         "  c: \"x # y\"     # the c\n"
                         "  d: 2\n"
                         "e: [1, 2]         # the e\n";
  std::map<std::string, SettingDoc> got;
  for (const auto& d : describe_settings(file)) got[d.key] = d;
  REQUIRE(got.size() == 4);
  CHECK(got["a.b"].doc == "the b and more of it");
  CHECK(got["a.c"].doc == "the c");
  CHECK(got["a.c"].default_value == "x # y");
  CHECK(got["a.d"].doc.empty());
  CHECK(got["e"].doc == "the e");
}

TEST_CASE("every number in the defaults files has a range rule, and every rule a key in them", "[config]") {
  const auto configs = test::source_dir() / "configs";
  std::map<std::string, std::string> keys;  // key -> its default value, over the three defaults files
  for (const char* file : {"defaults.yaml", "mask_defaults.yaml", "separable_defaults.yaml"}) {
    const auto config = Config::load({}, {}, configs / file);
    for (const auto& [key, value] : config.values()) keys[key] = value;
  }
  const auto ranged = Config::ranged_keys();
  for (const auto& key : ranged) {
    INFO("range rule for " << key);
    CHECK(keys.count(key) == 1);  // a rule for a key no trainer has drifted away from the defaults
  }
  // Seeds and counts of steps between logs take any non-negative integer; every other number
  // has its range declared.
  auto is_number = [](const std::string& v) {
    char* end = nullptr;
    std::strtod(v.c_str(), &end);
    return !v.empty() && end == v.c_str() + v.size();
  };
  for (const auto& [key, value] : keys) {
    if (!is_number(value) || key.size() >= 4 && key.compare(key.size() - 4, 4, "seed") == 0) continue;
    INFO(key << " = " << value << " has no range rule (its option table's row)");
    CHECK(std::find(ranged.begin(), ranged.end(), key) != ranged.end());
  }
}

TEST_CASE(
    "FusedAdam updates as torch::optim::Adam: plain and channels-last weights, weight decay, amsgrad, no gradient",
    "[nn]") {
  torch::manual_seed(16);
  const auto make_params = [] {
    torch::manual_seed(17);
    return std::vector<torch::Tensor>{
        torch::randn({8, 3, 3, 3}).contiguous(at::MemoryFormat::ChannelsLast).requires_grad_(),  // a conv's weight
        torch::randn({8}).requires_grad_(), torch::randn({5, 7}).requires_grad_(),
        torch::randn({4}).requires_grad_()};  // the last never gets a gradient
  };
  auto ours = make_params(), theirs = make_params();
  const auto groups = [](const std::vector<torch::Tensor>& p) {
    std::vector<torch::optim::OptimizerParamGroup> g;
    g.emplace_back(std::vector<torch::Tensor>{p[0], p[1], p[3]}, std::make_unique<torch::optim::AdamOptions>(1e-2));
    auto decayed = std::make_unique<torch::optim::AdamOptions>(3e-2);
    decayed->weight_decay(0.1).betas({0.8, 0.99});
    g.emplace_back(std::vector<torch::Tensor>{p[2]}, std::move(decayed));
    return g;
  };
  FusedAdam fused(groups(ours), torch::optim::AdamOptions(1e-2));
  torch::optim::Adam reference(groups(theirs), torch::optim::AdamOptions(1e-2));
  for (int step = 0; step < 6; ++step) {
    const auto target = torch::randn({1});
    for (auto* set : {&ours, &theirs}) {
      auto& p = *set;
      ((p[0] * p[0]).sum() * target + p[1].sin().sum() + (p[2] - target).pow(2).sum()).backward();
    }
    fused.step();
    reference.step();
    CHECK(fused.one_pass_updates() == 3);  // all but the parameter without a gradient
    for (size_t i = 0; i < ours.size(); ++i) {
      INFO("step " << step << " parameter " << i);
      CHECK(torch::allclose(ours[i], theirs[i], 1e-5, 1e-7));
    }
    fused.zero_grad();
    reference.zero_grad();
  }
  CHECK(ours[0].is_contiguous(at::MemoryFormat::ChannelsLast));
  CHECK(torch::equal(ours[3], theirs[3]));  // no gradient, no update, no state
  {  // moments read back from a checkpoint are contiguous: still one pass, the same update
    auto& state = static_cast<torch::optim::AdamParamState&>(
        *fused.state().at(c10::guts::to_string(ours[0].unsafeGetTensorImpl())));
    state.exp_avg(state.exp_avg().contiguous());
    REQUIRE_FALSE(state.exp_avg().is_contiguous(at::MemoryFormat::ChannelsLast));
    ((ours[0] * ours[0]).sum() + ours[1].sum() + ours[2].sum()).backward();
    ((theirs[0] * theirs[0]).sum() + theirs[1].sum() + theirs[2].sum()).backward();
    fused.step(), reference.step();
    CHECK(fused.one_pass_updates() == 3);
    CHECK(torch::allclose(ours[0], theirs[0], 1e-5, 1e-7));
  }
  CHECK(fused.state().size() == reference.state().size());  // the state a checkpoint saves
  // amsgrad takes torch::optim::Adam's own update; a gradient in another layout too.
  auto a = torch::randn({6}).requires_grad_(), b = a.detach().clone().requires_grad_();
  FusedAdam fused_ams({a}, torch::optim::AdamOptions(1e-2).amsgrad(true));
  torch::optim::Adam reference_ams({b}, torch::optim::AdamOptions(1e-2).amsgrad(true));
  for (int step = 0; step < 3; ++step) {
    (a * a).sum().backward(), (b * b).sum().backward();
    fused_ams.step(), reference_ams.step();
    CHECK(fused_ams.one_pass_updates() == 0);
    fused_ams.zero_grad(), reference_ams.zero_grad();
  }
  CHECK(torch::allclose(a, b, 1e-6, 1e-8));
}
