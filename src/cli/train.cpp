// flatnet train / export / import / infer: the FlatNet reconstruction network's commands.
#include <iostream>

#include <opencv2/core/version.hpp>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "core/precision.hpp"
#include "core/util.hpp"
#include "io/dataset.hpp"
#include "optics/simulator.hpp"
#include "nn/onnx_export.hpp"
#include "recon/infer.hpp"
#include "recon/opencv_engine.hpp"
#include "recon/run.hpp"
#include "train/distributed.hpp"
#include "train/gan_trainer.hpp"

namespace flatnet::cli {

namespace {

TrainOptions train_options(const Config& c, const std::filesystem::path& out) {
  TrainOptions t;
  t.iterations = c.integer("train.iterations");
  t.batch = c.integer("train.batch");
  t.lr = c.num("train.lr");
  t.lr_discriminator = c.num("train.lr_discriminator");
  t.lr_inversion_scale = c.num("train.lr_inversion_scale");
  t.lr_halve_every = c.integer("train.lr_halve_every");
  t.schedule = parse_lr_schedule(c.str("train.schedule"));
  t.w_ssim = c.num("loss.ssim");
  t.ema_decay = c.num("train.ema_decay");
  t.crop = c.integer("train.crop");
  require(t.crop == 0 || (t.crop >= 16 && t.crop % 16 == 0), "train.crop",
          "must be 0 or a multiple of 16 (the U-Net halves it 4 times)");
  require(t.ema_decay >= 0 && t.ema_decay < 1, "train.ema_decay", "must lie in [0, 1)");
  t.bf16 = resolve_precision(c.str("train.precision"), "train.precision") == Precision::bf16;
  t.discriminator_warmup = c.integer("train.discriminator_warmup");
  t.noise_augment = c.num("train.noise_augment");
  t.seed = static_cast<uint64_t>(c.integer("train.seed"));
  t.workers = static_cast<int>(c.integer("train.workers"));
  t.val_every = std::max<int64_t>(1, c.integer("train.val_every"));
  t.log_every = std::max<int64_t>(1, c.integer("train.log_every"));
  t.w_mse = c.num("loss.mse");
  t.w_perceptual = c.num("loss.perceptual");
  t.w_adversarial = c.num("loss.adversarial");
  t.real_label_min = c.num("discriminator.real_label_min");
  t.fake_label_max = c.num("discriminator.fake_label_max");
  require(t.real_label_min >= 0 && t.real_label_min <= 1 && t.fake_label_max >= 0 && t.fake_label_max <= 1,
          "discriminator", "label smoothing bounds must lie within [0, 1] (BCE needs targets in [0, 1])");
  require(t.batch >= 1 && t.iterations >= 1, "train", "batch and iterations must be positive");
  require(t.w_mse >= 0 && t.w_perceptual >= 0 && t.w_adversarial >= 0 && t.w_ssim >= 0, "loss",
          "weights must be non-negative");
  require(t.w_mse + t.w_perceptual + t.w_adversarial + t.w_ssim > 0, "loss", "every weight is 0: nothing to train on");
  t.channels_last = c.flag("train.channels_last");
  t.gemm_upsample = c.flag("train.gemm_upsample");
  t.check_sync_every = c.integer("train.check_sync_every");
  t.out = out;
  return t;
}

// Training and validation sources the config describes.
std::pair<std::shared_ptr<const PairSource>, std::shared_ptr<const PairSource>> data_sources(
    const Config& c, const CameraConfig& camera) {
  const auto source = c.str("data.source");
  if (source == "dataset") {
    DatasetLists train, val;
    const auto dir = c.path("data.dataset");
    if (!dir.empty()) {
      train = split_lists(dir, "train");
      val = split_lists(dir, "val");
    } else {
      require(!c.str("data.train_meas").empty(), "data",
              "set data.dataset, or data.train_meas/train_gt/val_meas/val_gt");
      train = {c.path("data.train_meas"), c.path("data.train_gt"), c.path("data.root")};
      val = {c.path("data.val_meas"), c.path("data.val_gt"), c.path("data.root")};
    }
    return {std::make_shared<DiskPairs>(read_pairs(train), camera),
            std::make_shared<DiskPairs>(read_pairs(val), camera)};
  }
  if (source == "simulate") {
    require(!camera.rig.empty(), "data.camera", "names no rig; on-the-fly simulation needs the true response");
    auto rig = std::make_shared<const Rig>(load_rig(camera.rig));
    auto [train_images, val_images] =
        split_image_files(c.path("data.images"), c.num("data.val_fraction"), c.integer("data.split_seed"));
    const auto seed = static_cast<uint64_t>(c.integer("train.seed"));
    LightAugment light;
    light.exposure_probability = c.num("data.light.exposure_probability");
    light.exposure_min = c.num("data.light.exposure_min");
    light.exposure_max = c.num("data.light.exposure_max");
    light.lamp_probability = c.num("data.light.lamp_probability");
    light.lamp_min = c.num("data.light.lamp_min");
    light.lamp_max = c.num("data.light.lamp_max");
    require(light.exposure_min > 0 && light.exposure_min <= light.exposure_max && light.lamp_min > 0 &&
                light.lamp_min <= light.lamp_max,
            "data.light", "needs 0 < exposure_min <= exposure_max and 0 < lamp_min <= lamp_max");
    require(light.exposure_probability >= 0 && light.exposure_probability <= 1 && light.lamp_probability >= 0 &&
                light.lamp_probability <= 1,
            "data.light", "probabilities must lie in [0, 1]");
    // Validation stays on display captures (the held-out set's conditions).
    return {std::make_shared<SimulatedPairs>(train_images, rig, camera, seed, light),
            std::make_shared<SimulatedPairs>(val_images, rig, camera, seed + 1)};
  }
  throw Error("config: data.source must be dataset or simulate, got '" + source + "'");
}

void require_no_light_augment_on_disk(const Config& c) {
  if (c.str("data.source") == "dataset" &&
      (c.num("data.light.exposure_probability") > 0 || c.num("data.light.lamp_probability") > 0))
    throw Error(
        "data.light: light augmentation simulates each sample; it needs data.source: simulate (with data.images)");
}

CameraConfig camera_of(const Config& c) { return load_camera_config(c.path("data.camera")); }

Vgg16Features vgg_if_needed(const Config& c) {
  if (c.num("loss.perceptual") <= 0) return Vgg16Features(nullptr);
  return load_vgg16(c.path("loss.vgg_file"), c.flag("loss.vgg_normalize"));
}

// "key (run: a, --config: b), ..." for every setting in which two configs differ (paths compared
// resolved, as a checkpoint records them); empty when they agree.
std::string differing_settings(const Config& run, const Config& given) {
  const auto a = Config::from_text(run.to_yaml(), "run").values();
  const auto b = Config::from_text(given.to_yaml(), "--config").values();
  std::string out;
  for (const auto& [key, value] : a) {
    const auto it = b.find(key);
    if (it != b.end() && it->second != value)
      out += (out.empty() ? "" : ", ") + key + " (run: " + value + ", --config: " + it->second + ")";
  }
  return out;
}

}  // namespace

int train(int argc, char** argv) {
  cxxopts::Options o("flatnet train", "Train a FlatNet reconstruction network (GAN, FlatNet-sep).");
  o.add_options()("config", "experiment config (configs/*.yaml); defaults.yaml alone when absent",
                  cxxopts::value<std::string>())("set", "override a setting: --set train.iterations=100 (repeatable)",
                                                 cxxopts::value<std::vector<std::string>>())(
      "out", "run folder (checkpoints, logs, model.flatnet)", cxxopts::value<std::string>())(
      "resume", "continue the run in --out from its latest checkpoint")(
      "init-from",
      "start from a model file's generator weights (a shipped model, or one from another camera's run) "
      "with fresh optimisers; the config must describe the same architecture",
      cxxopts::value<std::string>())("precision", "auto|fp32|bf16: overrides train.precision",
                                     cxxopts::value<std::string>());
  o.add_options("distributed (defaults: torchrun's WORLD_SIZE, RANK, MASTER_ADDR, MASTER_PORT)")(
      "world-size", "processes in the job", cxxopts::value<int>())(
      "rank", "this process, 0..world-size-1", cxxopts::value<int>())("master-addr", "host of rank 0 (rendezvous)",
                                                                      cxxopts::value<std::string>())(
      "master-port", "TCP port of the rendezvous on rank 0", cxxopts::value<int>())(
      "dist-timeout", "seconds a collective may wait before the job fails",
      cxxopts::value<double>()->default_value("300"));
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("out"), "train", "--out DIR is required");
  auto dist = distributed_from_env();
  if (r.count("world-size")) dist.world_size = r["world-size"].as<int>();
  if (r.count("rank")) dist.rank = r["rank"].as<int>();
  if (r.count("master-addr")) dist.master_addr = r["master-addr"].as<std::string>();
  if (r.count("master-port")) dist.master_port = r["master-port"].as<int>();
  dist.timeout_s = r["dist-timeout"].as<double>();
  require(dist.world_size >= 1 && dist.rank >= 0 && dist.rank < dist.world_size, "--rank",
          "must lie in [0, world size " + std::to_string(dist.world_size) + ")");
  const bool writer = dist.rank == 0;
  const std::filesystem::path out = r["out"].as<std::string>();
  auto sets = set_overrides(r);
  if (r.count("precision")) sets.push_back("train.precision=" + r["precision"].as<std::string>());
  const auto latest = out / "latest.ckpt";
  const bool resume = r.count("resume") > 0;
  Config config;
  if (resume) {
    require(std::filesystem::exists(latest), latest, "nothing to resume (no checkpoint)");
    config = checkpoint_settings(latest).first;
    for (const auto& s : sets) config.set(s);
    config.check_ranges("--set");
    if (r.count("config")) {  // the same command line again is fine; another config is not silently ignored
      const auto differences = differing_settings(config, Config::load(r["config"].as<std::string>(), sets));
      require(differences.empty(), "--config",
              "--resume continues with the run's own config (" + (out / "config.yaml").string() +
                  "), which differs in " + differences + "; change single settings with --set key=value");
    }
  } else {
    require(!writer || !std::filesystem::exists(latest), out,
            "already holds a training run; continue it with --resume or choose another --out");
    config = Config::load(r.count("config") ? r["config"].as<std::string>() : "", sets);
  }
  require(!(resume && r.count("init-from")), "--init-from", "starts a new run; it cannot be combined with --resume");
  require_no_light_augment_on_disk(config);
  // Everything that can fail on bad input is checked before anything is written.
  const auto camera = camera_of(config);
  auto vgg = vgg_if_needed(config);
  auto opts = train_options(config, out);
  require(opts.crop <= camera.scene_size, "train.crop",
          std::to_string(opts.crop) + " exceeds the camera's " + std::to_string(camera.scene_size) +
              "-pixel scene (0: whole scenes)");
  auto [train_src, val_src] = data_sources(config, camera);
  torch::manual_seed(opts.seed);
  Generator g(generator_options(config, camera, !resume && !r.count("init-from")));
  if (r.count("init-from")) {
    init_generator_from(r["init-from"].as<std::string>(), g);
    std::cerr << "initialised from " << r["init-from"].as<std::string>() << " (fresh optimisers)\n";
  }
  if (writer) {
    const auto p = resolve_precision(config.str("train.precision"), "train.precision");
    if (p == Precision::bf16) request_amx_permission();
    std::cerr << "precision: " << describe_precision(p) << "\n";
  }
  Discriminator d(discriminator_options(config));
  std::cerr << "loading "
            << (config.integer("train.val_count") > 0 ? std::min(config.integer("train.val_count"), val_src->size())
                                                      : val_src->size())
            << " validation samples...\n";
  auto val = load_all(*val_src, config.integer("train.val_count"), std::max(1, opts.workers));
  if (writer) {
    std::filesystem::create_directories(out);
    write_text_atomically(out / "config.yaml", config.to_yaml());
  }
  std::unique_ptr<ProcessGroup> group;
  if (dist.world_size > 1) {
    std::cerr << "rank " << dist.rank << " of " << dist.world_size << ": joining " << dist.master_addr << ":"
              << dist.master_port << "...\n";
    group = std::make_unique<ProcessGroup>(dist);
  }
  GanTrainer trainer(g, d, vgg, train_src, std::move(val), opts, config, camera);
  if (resume) trainer.resume(latest);  // every rank reads rank 0's checkpoint (a shared or copied folder)
  trainer.set_distributed(group.get());
  watch_interrupts();
  std::cerr << "training on " << train_src->size() << " pairs, " << opts.iterations << " steps of batch " << opts.batch
            << (dist.world_size > 1 ? " per rank x " + std::to_string(dist.world_size) + " ranks" : "") << " ("
            << config.str("model.input") << " + " << config.str("model.enhancer") << ", width "
            << config.integer("model.unet.width") << ")\n";
  const auto s = trainer.run();
  if (!writer) {
    std::cout << "rank " << dist.rank << ": steps " << s.first_step << ".." << s.last_step << " done\n";
    return interrupted() ? 130 : 0;
  }
  std::cout << "steps " << s.first_step << ".." << s.last_step << " in " << format_duration(s.seconds) << " ("
            << s.steps_per_s << " steps/s, data wait " << s.loader_wait_s << " s)\n"
            << "validation: last PSNR " << s.last_psnr << " SSIM " << s.last_ssim << ", best PSNR " << s.best_psnr
            << "\nmodel: " << (out / "model.flatnet").string() << "\n";
  if (interrupted()) {
    std::cout << "interrupted: continue with `flatnet train --out " << out.string() << " --resume`\n";
    return 130;
  }
  return 0;
}

int export_model(int argc, char** argv) {
  cxxopts::Options o("flatnet export", "Export a trained model: a self-contained model file, or a PyTorch state_dict.");
  o.add_options()("checkpoint", "training checkpoint (RUN/best.ckpt or latest.ckpt)", cxxopts::value<std::string>())(
      "model", "model file (instead of --checkpoint; for --state-dict)", cxxopts::value<std::string>())(
      "out", "file to write", cxxopts::value<std::string>())(
      "state-dict", "write torch.save(state_dict) with FlatNet-sep's parameter names instead of a model file")(
      "flatnet-checkpoint", "write FlatNet's checkpoint layout {'gen_state_dict': state_dict} (its main.py loads it)")(
      "onnx",
      "write an ONNX graph to this file (input meas {1,4,rows,cols}, output image {1,3,N,N}; "
      "OpenCV DNN reads it: `flatnet infer --engine opencv`)",
      cxxopts::value<std::string>())("force", "replace an existing --out file");
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require((r.count("out") + r.count("onnx") == 1) && (r.count("checkpoint") + r.count("model") == 1), "export",
          "one of --checkpoint CKPT or --model MODEL, and one of --out FILE or --onnx FILE, are required");
  require(r.count("state-dict") + r.count("flatnet-checkpoint") + r.count("onnx") <= 1, "export",
          "give one of --state-dict, --flatnet-checkpoint and --onnx");
  const std::filesystem::path out = r.count("onnx") ? r["onnx"].as<std::string>() : r["out"].as<std::string>();
  const std::string input = r.count("checkpoint") ? r["checkpoint"].as<std::string>() : r["model"].as<std::string>();
  require_new_output(out, r.count("force") > 0, {input});
  bool average = false;
  auto m = r.count("checkpoint") ? model_from_checkpoint(input, &average) : load_model_file(input);
  if (average) std::cerr << "exporting the moving average of the weights (train.ema_decay)\n";
  if (r.count("onnx")) {
    const auto rep = export_onnx(out, m.generator, m.camera);
    std::cout << "wrote ONNX " << out.string() << " (" << rep.nodes << " nodes, " << rep.initializers
              << " weight tensors, " << rep.bytes / 1e6 << " MB; input meas {1,4," << m.camera.raw.crop[2] << ","
              << m.camera.raw.crop[3] << "}, output image {1,3," << m.camera.scene_size << "," << m.camera.scene_size
              << "}; checked by ONNX's checker)\n";
  } else if (r.count("state-dict") || r.count("flatnet-checkpoint")) {
    const bool flatnet_layout = r.count("flatnet-checkpoint") > 0;
    export_state_dict(out, m.generator,
                      flatnet_layout ? StateDictLayout::flatnet_checkpoint : StateDictLayout::state_dict);
    std::cout << "wrote " << (flatnet_layout ? "FlatNet checkpoint " : "state dict ") << out.string() << " ("
              << m.generator->named_parameters().size() << " parameters; python: "
              << (flatnet_layout ? "G.load_state_dict(torch.load(path)['gen_state_dict'])"
                                 : "model.load_state_dict(torch.load(path))")
              << ")\n";
  } else {
    save_model_file(out, m.generator, m.config, m.camera);
    std::cout << "wrote model " << out.string() << "\n";
  }
  return 0;
}

int import_model(int argc, char** argv) {
  cxxopts::Options o("flatnet import", "Make a model file from a PyTorch state_dict with FlatNet-sep's names.");
  o.add_options()("state-dict", "torch.save'd state dict (or FlatNet checkpoint with gen_state_dict)",
                  cxxopts::value<std::string>())(
      "config", "config describing the architecture (e.g. configs/flatnet_paper.yaml)", cxxopts::value<std::string>())(
      "set", "override a setting (repeatable)", cxxopts::value<std::vector<std::string>>())(
      "camera", "camera the weights were trained for (default: the config's data.camera)",
      cxxopts::value<std::string>())("out", "model file to write", cxxopts::value<std::string>())(
      "verbose", "list the file's tensors that the model does not use")("force", "replace an existing --out file");
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("state-dict") && r.count("out"), "import", "--state-dict FILE and --out MODEL are required");
  const std::filesystem::path out = r["out"].as<std::string>();
  require_new_output(out, r.count("force") > 0, {r["state-dict"].as<std::string>()});
  const auto sets = set_overrides(r);
  auto config = Config::load(r.count("config") ? r["config"].as<std::string>() : "", sets);
  const auto camera = r.count("camera") ? load_camera_config(r["camera"].as<std::string>()) : camera_of(config);
  Generator g(generator_options(config, camera, false));
  const auto rep = import_state_dict(r["state-dict"].as<std::string>(), g);
  save_model_file(out, g, config, camera);
  std::cout << "read " << rep.used << " tensors from " << rep.source
            << (rep.data_parallel ? " (DataParallel names)" : "") << "; " << rep.unused.size() << " unused"
            << (rep.unused.empty() || r.count("verbose") ? "" : " (--verbose lists them)") << "\n";
  if (r.count("verbose"))
    for (const auto& name : rep.unused) std::cout << "  unused: " << name << "\n";
  std::cout << "wrote model " << out.string() << "\n";
  return 0;
}

int infer(int argc, char** argv) {
  cxxopts::Options o("flatnet infer", "Reconstruct raw captures with a trained FlatNet model.");
  o.add_options()("model", "model file (models/*.flatnet or RUN/model.flatnet; an .onnx file with --engine opencv)",
                  cxxopts::value<std::string>())(
      "engine", "libtorch, or opencv: an ONNX file from `flatnet export --onnx` through OpenCV's DNN module",
      cxxopts::value<std::string>()->default_value("libtorch"))("input", "raw capture PNG or folder of them",
                                                                cxxopts::value<std::string>())(
      "out", "output folder (PNGs with the captures' names)", cxxopts::value<std::string>())(
      "camera", "camera .yaml whose preprocessing to use (default: the model's)", cxxopts::value<std::string>())(
      "batch", "captures per batch", cxxopts::value<int>()->default_value("4"))(
      "levers",
      "exact inference speed-ups: none, or a list of fold, channels-last, gemm-up, onednn (bf16 and onednn: see "
      "--precision)",
      cxxopts::value<std::string>()->default_value("fold,channels-last,gemm-up,onednn"));
  add_precision(o);
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("model") && r.count("input") && r.count("out"), "infer",
          "--model MODEL, --input DIR|FILE and --out DIR are required");
  const auto engine = r["engine"].as<std::string>();
  require(engine == "libtorch" || engine == "opencv", "--engine", "libtorch or opencv expected, got '" + engine + "'");
  InferOptions opt;
  opt.out = r["out"].as<std::string>();
  opt.batch = std::max(1, r["batch"].as<int>());
  const auto captures = collect_captures(r["input"].as<std::string>());
  InferReport rep;
  if (engine == "opencv") {
    OpenCvEngine net(r["model"].as<std::string>());
    const auto camera = r.count("camera") ? load_camera_config(r["camera"].as<std::string>()) : net.camera();
    net.check_camera(camera);
    std::cerr << "engine: OpenCV DNN " << CV_VERSION << " (fp32; --levers and --precision apply to libtorch)\n";
    rep = infer_files([&](const torch::Tensor& planes) { return net.forward(planes); }, camera, captures, opt);
  } else {
    auto m = load_model_file(r["model"].as<std::string>());
    const auto camera = r.count("camera") ? load_camera_config(r["camera"].as<std::string>()) : m.camera;
    opt.levers = parse_inference_levers(r["levers"].as<std::string>());
    if (precision_from(r) == Precision::bf16)
      opt.levers.bf16 = true;  // the enhancer in bf16; inversion and sigmoid stay fp32
    rep = infer_files(m.generator, camera, captures, opt);
  }
  std::cout << "flatnet: " << rep.count << " captures -> " << opt.out.string() << " (" << rep.images_per_s
            << " images/s, " << rep.model_ms_per_image << " ms per image in the network)\n";
  return 0;
}

}  // namespace flatnet::cli
