#include "bench/bench.hpp"

#include <malloc.h>

#include <fstream>

#include <torch/csrc/autograd/profiler_kineto.h>

#include "io/camera_config.hpp"
#include "core/error.hpp"
#include "core/precision.hpp"
#include "core/util.hpp"
#include "io/raw.hpp"
#include "nn/onednn_conv.hpp"
#include "optics/camera.hpp"
#include "optics/mask.hpp"
#include "recon/reconstructor.hpp"
#include "recon/tikhonov.hpp"
#include "nn/fused_adam.hpp"
#include "train/data.hpp"
#include "train/gan_trainer.hpp"

namespace flatnet {

namespace {

constexpr int64_t kRows = 500, kCols = 620, kScene = 256;

double now_ms() {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

// Runs fn once under LibTorch's profiler and sums its operators by name (and, with `shapes`, by
// input shapes and types). Self time: an event's
// duration less that of the events nested directly inside it on the same thread.
std::vector<OpTime> profile_once(const std::function<void()>& fn, bool shapes) {
  namespace prof = torch::profiler::impl;
  const prof::ProfilerConfig config(prof::ProfilerState::KINETO, shapes);
  const std::set<prof::ActivityType> activities = {prof::ActivityType::CPU};
  torch::autograd::profiler::prepareProfiler(config, activities);
  torch::autograd::profiler::enableProfiler(config, activities);
  fn();
  const auto result = torch::autograd::profiler::disableProfiler();
  struct Span {
    std::string name;
    uint64_t thread, start, end;
  };
  std::vector<Span> spans;
  for (const auto& e : result->events()) {
    std::string name = e.name();
    if (shapes && e.hasShapes()) {  // e.g. "aten::bmm {4,256,500} {4,500,620} float float"
      for (const auto& s : e.shapes()) {
        if (s.empty()) continue;  // a scalar or an absent argument
        std::string dims;
        for (auto d : s) dims += (dims.empty() ? "" : ",") + std::to_string(d);
        name += " {" + dims + "}";
      }
      for (const auto& t : e.dtypes())
        if (!t.empty() && t != "Scalar") name += " " + t;
    }
    spans.push_back({name, e.startThreadId(), e.startUs(), e.startUs() + e.durationUs()});
  }
  std::sort(spans.begin(), spans.end(), [](const Span& a, const Span& b) {
    return std::tie(a.thread, a.start, b.end) < std::tie(b.thread, b.start, a.end);  // parents first
  });
  std::map<std::string, OpTime> by_name;
  std::vector<std::pair<const Span*, double>> open;  // enclosing spans and their children's time
  auto close = [&](const Span& s, double children_us) {
    auto& op = by_name[s.name];
    op.name = s.name;
    ++op.calls;
    op.total_ms += (s.end - s.start) / 1e3;
    op.self_ms += std::max(0.0, (s.end - s.start) - children_us) / 1e3;
  };
  for (const auto& s : spans) {
    while (!open.empty() && (open.back().first->thread != s.thread || open.back().first->end <= s.start)) {
      close(*open.back().first, open.back().second);
      open.pop_back();
    }
    if (!open.empty()) open.back().second += static_cast<double>(s.end - s.start);
    open.emplace_back(&s, 0.0);
  }
  for (; !open.empty(); open.pop_back()) close(*open.back().first, open.back().second);
  std::vector<OpTime> ops;
  for (auto& [name, op] : by_name) ops.push_back(op);
  std::sort(ops.begin(), ops.end(), [](const OpTime& a, const OpTime& b) { return a.self_ms > b.self_ms; });
  return ops;
}

// Times fn: `warmup` untimed calls, then `repeats` timed ones (and one profiled, if asked).
BenchRow time_row(const std::string& name, const std::string& what, const BenchOptions& o,
                  const std::function<void()>& fn) {
  BenchRow row;
  row.name = name;
  row.what = what;
  for (int i = 0; i < o.warmup; ++i) fn();
  for (int i = 0; i < std::max(1, o.repeats); ++i) {
    const double t = now_ms();
    fn();
    row.ms.push_back(now_ms() - t);
  }
  auto sorted = row.ms;
  std::sort(sorted.begin(), sorted.end());
  row.median_ms = sorted[sorted.size() / 2];
  if (sorted.size() % 2 == 0) row.median_ms = 0.5 * (sorted[sorted.size() / 2 - 1] + sorted[sorted.size() / 2]);
  row.min_ms = sorted.front();
  // The profiler's first run pays for its own set-up (a training step's operators summed to 340-400
  // ms there against 246 ms in the next, `--rows train_cpu`): the second is the one reported.
  if (o.profile) {
    profile_once(fn, o.profile_shapes);
    row.ops = profile_once(fn, o.profile_shapes);
  }
  return row;
}

// The practical peak of this machine for one kind of kernel: a large GEMM (2048^3) or a 3x3
// convolution at U-Net scale (batch 4, 128 -> 128 channels, 128x128, channels-last), in fp32 or bf16,
// through the same LibTorch paths the models use (OpenBLAS / oneDNN).
BenchRow peak_row(const std::string& name, const BenchOptions& o) {
  const bool bf16 = name.size() > 5 && name.substr(name.size() - 5) == "_bf16";
  const auto dtype = bf16 ? torch::kBFloat16 : torch::kFloat32;
  c10::InferenceMode guard;
  BenchRow row;
  if (name.rfind("peak_gemm", 0) == 0) {
    const int64_t n = 2048;
    const auto a = torch::randn({n, n}).to(dtype), b = torch::randn({n, n}).to(dtype);
    row = time_row(name, std::string("practical peak: GEMM 2048x2048x2048, ") + (bf16 ? "bf16" : "fp32"), o,
                   [&] { torch::mm(a, b); });
    row.gflop = 2.0 * n * n * n / 1e9;
    row.peak_kind = bf16 ? "bf16" : "fp32";
  } else {
    const auto x = torch::randn({4, 128, 128, 128}).to(dtype).contiguous(at::MemoryFormat::ChannelsLast);
    const auto w = (torch::randn({128, 128, 3, 3}) * 0.03).to(dtype).contiguous(at::MemoryFormat::ChannelsLast);
    row =
        time_row(name,
                 std::string("practical peak: 3x3 convolution, batch 4, 128->128 channels, 128x128, channels-last, ") +
                     (bf16 ? "bf16" : "fp32"),
                 o, [&] { torch::conv2d(x, w, {}, 1, 1); });
    row.gflop = 2.0 * 4 * 128 * 128 * 128 * 128 * 9 / 1e9;
    row.peak_kind = bf16 ? "bf16" : "fp32";
  }
  row.per_second = 1000.0 / row.median_ms;
  return row;
}

Calibration random_calibration() {
  auto gen = at::detail::createCPUGenerator(0);
  Calibration c;
  c.P = at::randn({4, kRows, kScene}, gen) / std::sqrt(static_cast<double>(kRows));
  c.Q = at::randn({4, kCols, kScene}, gen) / std::sqrt(static_cast<double>(kCols));
  return c;
}

GeneratorOptions generator_for(int64_t width) {
  GeneratorOptions g;
  g.unet.width = width;
  g.inversion.phil =
      torch::randn({kRows, kScene, 1}) / std::sqrt(static_cast<double>(kRows));  // FlatNet: shared W1, W2
  g.inversion.phir = torch::randn({kCols, kScene, 1}) / std::sqrt(static_cast<double>(kCols));
  return g;
}

BenchRow infer_row(const std::string& name, int64_t width, const BenchOptions& o) {
  torch::manual_seed(0);
  auto levers = o.levers;
  levers.bf16 = levers.bf16 || o.bf16;
  CameraConfig camera;  // the shapes of the reference camera, plane centring (as the model)
  camera.raw.crop = {0, 0, kRows, kCols};
  camera.scene_size = kScene;
  const auto engine = make_flatnet(Generator(generator_for(width)), camera, levers);
  const auto Y = torch::randn({1, 4, kRows, kCols}) * 0.05;
  std::string names = std::string(levers.fold_batchnorm ? " fold" : "") +
                      (levers.channels_last ? " channels-last" : "") + (levers.gemm_upsample ? " gemm-up" : "") +
                      (levers.bf16 ? " bf16" : "") + (levers.onednn_active() ? " onednn" : "");
  auto row = time_row(name,
                      "FlatNet-sep U-Net width " + std::to_string(width) +
                          ", batch 1, levers:" + (names.empty() ? std::string(" none") : names),
                      o, [&] { engine->reconstruct(Y); });
  row.per_second = 1000.0 / row.median_ms;
  // The work, counted on the same model without levers (the oneDNN lever bypasses ATen's operators,
  // which the profiler counts; folding removes only the batch norms' few FLOPs).
  Generator plain(generator_for(width));
  plain->eval();
  c10::InferenceMode guard;
  row.gflop = count_gflop([&] { plain->forward(Y); });
  row.peak_kind = levers.bf16 ? "bf16" : "fp32";
  return row;
}

BenchRow train_row(const std::string& name, int64_t width, bool paper, const BenchOptions& o) {
  torch::manual_seed(0);
  Generator g(generator_for(width));
  g->prepare_training(o.levers);
  DiscriminatorOptions dopt;
  Discriminator d(dopt);
  if (o.levers.channels_last) weights_to_channels_last(*d);    // as GanTrainer
  Vgg16Features vgg(false);                                    // random weights: the cost is what is measured
  if (o.levers.channels_last) weights_to_channels_last(*vgg);  // as GanTrainer
  TrainOptions t;
  t.batch = 4;
  t.w_mse = 1.0;
  t.w_perceptual = paper ? 1.2 : 0.0;
  t.w_adversarial = paper ? 0.6 : 1e-3;
  t.bf16 = o.bf16;
  FusedAdam opt_g(g->parameters(), torch::optim::AdamOptions(1e-4).betas({0.9, 0.999}));  // as GanTrainer
  FusedAdam opt_d(d->parameters(), torch::optim::AdamOptions(1e-4).betas({0.9, 0.999}));
  g->train();
  d->train();
  Batch batch;
  batch.meas = torch::randn({4, 4, kRows, kCols}) * 0.05;
  batch.gt = torch::rand({4, 3, kScene, kScene});
  int64_t step = 0;
  auto row = time_row(name,
                      "one GAN step (D then G), batch 4, U-Net width " + std::to_string(width) + ", MSE" +
                          (paper ? " + 1.2 VGG-16 perceptual + 0.6 adversarial" : " + 1e-3 adversarial") + ", Adam" +
                          (o.levers.channels_last ? ", channels-last" : "") +
                          (o.levers.gemm_upsample ? ", gemm-up" : "") + (o.bf16 ? ", bf16 autocast" : ", fp32"),
                      o, [&] { gan_step(g, d, vgg, opt_g, opt_d, t, batch, step++); });
  row.per_second = 1000.0 / row.median_ms;
  // The step's work: forwards, backwards (count_gflop counts both gradients of every convolution,
  // which overstates the first layers' by their unneeded input gradient) and Adam.
  row.gflop = count_gflop([&] { gan_step(g, d, vgg, opt_g, opt_d, t, batch, step++); });
  row.peak_kind = o.bf16 ? "bf16" : "fp32";
  return row;
}

// One step of the shipped models' GAN recipe (configs/gan_transpose.yaml): U-Net width 32 reading
// the light level, batch 8, the enhancer on 128x128 crops, MSE + 0.2 (1 - SSIM) + 0.01 adversarial
// + 0.05 feature matching + 0.5 chroma, Adam. Data loading is not part of it (the loader row).
BenchRow train_recipe_row(const std::string& name, const BenchOptions& o) {
  torch::manual_seed(0);
  auto options = generator_for(32);
  options.level_input = true;
  options.unet.in_channels = 8;  // the first stage's 4 planes and their 4 light levels
  options.bn_momentum = options.unet.bn_momentum = 0.1;
  Generator g(options);
  g->prepare_training(o.levers);
  Discriminator d(DiscriminatorOptions{});
  if (o.levers.channels_last) weights_to_channels_last(*d);  // as GanTrainer
  Vgg16Features vgg(false);                                  // unused: the recipe has no perceptual term
  TrainOptions t;
  t.batch = 8;
  t.crop = 128;
  t.w_mse = 1.0;
  t.w_ssim = 0.2;
  t.w_perceptual = 0.0;
  t.w_adversarial = 0.01;
  t.w_feature_matching = 0.05;
  t.w_chroma = 0.5;
  t.bf16 = o.bf16;
  FusedAdam opt_g(g->parameters(), torch::optim::AdamOptions(1e-4));  // as GanTrainer
  FusedAdam opt_d(d->parameters(), torch::optim::AdamOptions(1e-4));
  g->train();
  d->train();
  Batch batch;
  batch.meas = torch::randn({8, 4, kRows, kCols}) * 0.05 + 0.3;
  batch.gt = torch::rand({8, 3, kScene, kScene});
  int64_t step = 0;
  auto row = time_row(name,
                      "one step of the shipped GAN recipe: U-Net width 32 + light level, batch 8, 128x128 crops, MSE + "
                      "0.2 SSIM + 0.01 adversarial + 0.05 feature matching + 0.5 chroma, Adam" +
                          std::string(o.bf16 ? ", bf16 autocast" : ", fp32"),
                      o, [&] { gan_step(g, d, vgg, opt_g, opt_d, t, batch, step++); });
  row.per_second = 1000.0 / row.median_ms;
  row.gflop = count_gflop([&] { gan_step(g, d, vgg, opt_g, opt_d, t, batch, step++); });
  row.peak_kind = o.bf16 ? "bf16" : "fp32";
  return row;
}

BenchRow mask_row(const BenchOptions& o) {
  MaskOptions mo;
  mo.rank = 1;
  MaskModel model(mo);
  WienerCamera cam;
  auto log_gamma = torch::tensor(std::log(1e-4)).set_requires_grad(true);
  auto params = model->parameters();
  params.push_back(log_gamma);
  torch::optim::Adam opt(params, torch::optim::AdamOptions(1e-2));
  const auto scenes = torch::rand({4, kScene, kScene});
  auto gen = at::detail::createCPUGenerator(0);
  auto row = time_row("mask_step",
                      "rank-1 511x511 mask: PSF, FFT capture + noise, Wiener, MSE, backward, Adam; batch 4", o, [&] {
                        const auto P = psf_spectrum(model->window());
                        const auto rec = wiener(capture(scenes, P, cam, gen), P, log_gamma.exp(), cam);
                        const auto loss = torch::mse_loss(rec, scenes);
                        opt.zero_grad();
                        loss.backward();
                        opt.step();
                      });
  row.per_second = 1000.0 / row.median_ms;
  return row;
}

}  // namespace

const std::vector<std::string>& bench_row_names() {
  static const std::vector<std::string> names = {"tikhonov",  "live_frame",  "simulator", "infer_paper",
                                                 "infer_cpu", "train_paper", "train_cpu", "train_recipe",
                                                 "mask_step", "loader"};
  return names;
}

std::vector<std::string> peak_row_names() {
  std::vector<std::string> names = {"peak_gemm_fp32", "peak_conv_fp32"};
  if (resolve_precision("auto") == Precision::bf16) {
    names.push_back("peak_gemm_bf16");
    names.push_back("peak_conv_bf16");
  }
  return names;
}

namespace {

// An operator call that does counted work: its FLOPs as the profiler gives them, or (transposed
// convolutions and convolution gradients, which it does not count) from its shapes.
struct CountedCall {
  std::string name;
  uint64_t thread, begin, end;
  double flops;
};

double shape_flops(const std::string& name, c10::ArrayRef<std::vector<int64_t>> shapes) {
  if (shapes.size() < 2 || shapes[0].size() != 4 || shapes[1].size() != 4) return 0;
  if (name == "aten::conv_transpose2d") {
    const auto &in = shapes[0], &w = shapes[1];  // {N,Cin,H,W}, {Cin,Cout/groups,kh,kw}
    return 2.0 * in[0] * in[1] * in[2] * in[3] * w[1] * w[2] * w[3];
  }
  if (name != "aten::convolution_backward" || shapes.size() < 3 || shapes[2].size() != 4) return 0;
  // The gradients of the input and of the weight, each as much work as the forward. A transposed
  // convolution's output is larger than its input (FlatNet's 2x2 stride-2 ups).
  const auto &grad_out = shapes[0], &in = shapes[1], &w = shapes[2];
  const bool transposed = grad_out[2] > in[2];
  const double forward = transposed ? 2.0 * in[0] * in[1] * in[2] * in[3] * w[1] * w[2] * w[3]
                                    : 2.0 * grad_out[0] * grad_out[1] * grad_out[2] * grad_out[3] * w[1] * w[2] * w[3];
  return 2 * forward;
}

// Whether a call runs inside another call of the same operator on the same thread. Under autocast,
// LibTorch's autocast kernel for aten::conv2d (or mm, addmm, ...) casts its inputs and calls the
// operator again: the profiler records both calls and gives each the whole product's FLOPs, which
// counted a bf16 step's forward convolutions twice.
bool nested_in_itself(size_t i, const std::vector<CountedCall>& calls) {
  const auto& e = calls[i];
  for (size_t j = 0; j < calls.size(); ++j) {
    const auto& outer = calls[j];
    if (j == i || outer.name != e.name || outer.thread != e.thread) continue;
    const bool inside = e.begin >= outer.begin && e.end <= outer.end;
    const bool same_span = e.begin == outer.begin && e.end == outer.end;
    if (inside && (!same_span || j < i)) return true;  // equal spans: the first recorded is the outer
  }
  return false;
}

}  // namespace

double count_gflop(const std::function<void()>& fn) {
  namespace prof = torch::profiler::impl;
  const prof::ProfilerConfig config(prof::ProfilerState::KINETO, /*report_input_shapes=*/true, false, false,
                                    /*with_flops=*/true);
  const std::set<prof::ActivityType> activities = {prof::ActivityType::CPU};
  torch::autograd::profiler::prepareProfiler(config, activities);
  torch::autograd::profiler::enableProfiler(config, activities);
  const auto onednn_before = onednn_flops();
  fn();
  const auto result = torch::autograd::profiler::disableProfiler();
  // flatnet's own oneDNN calls: the first stage's products, the training convolutions
  double flops = static_cast<double>(onednn_flops() - onednn_before);
  std::vector<CountedCall> calls;
  for (const auto& e : result->events()) {
    const double work = static_cast<double>(e.flops()) + (e.hasShapes() ? shape_flops(e.name(), e.shapes()) : 0.0);
    if (work > 0) calls.push_back({e.name(), e.startThreadId(), e.startUs(), e.startUs() + e.durationUs(), work});
  }
  for (size_t i = 0; i < calls.size(); ++i)
    if (!nested_in_itself(i, calls)) flops += calls[i].flops;
  return flops / 1e9;
}

bool bench_row_has_precision(const std::string& name) {
  return name.rfind("infer_", 0) == 0 || name.rfind("train_", 0) == 0;
}

double peak_rss_mb() {
  std::ifstream in("/proc/self/status");
  std::string line;
  while (std::getline(in, line))
    if (line.rfind("VmHWM:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;
  return 0;
}

void reset_peak_rss() {
  malloc_trim(0);  // the memory earlier rows freed (kept by keep_freed_memory) is not this row's
  std::ofstream out("/proc/self/clear_refs");
  out << "5";
}

BenchRow run_bench_row(const std::string& name, const BenchOptions& o) {
  reset_peak_rss();
  BenchRow row;
  if (name == "tikhonov") {
    const Tikhonov tik(random_calibration(), 1e-4);
    const auto Y = torch::randn({1, 4, kRows, kCols});
    c10::InferenceMode guard;
    row = time_row(name, "Tikhonov (SVD closed form) of one capture, 4 planes 500x620 -> 256x256", o, [&] { tik(Y); });
    row.per_second = 1000.0 / row.median_ms;
    // oneDNN's GEMMs are invisible to the profiler: counted from the shapes, per plane
    // Y U_R (2 h w N), U_L^T (.) (2 N h N), V_L (.) and (.) V_R^T (2 N^3 each).
    row.gflop =
        4.0 * (2.0 * kRows * kCols * kScene + 2.0 * kScene * kRows * kScene + 4.0 * kScene * kScene * kScene) / 1e9;
    row.peak_kind = "fp32";
  } else if (name == "live_frame") {
    const auto camera = load_camera_config(default_camera_path());
    const auto engine = make_classical(random_calibration(), camera, {ClassicalMethod::tikhonov, 1e-4});
    const auto codes = torch::randint(0, 1024, {camera.raw.raw_height, camera.raw.raw_width}, torch::kInt32);
    c10::InferenceMode guard;
    row = time_row(name, "live view's work per frame: 10-bit codes 1024x1280 -> planes -> Tikhonov -> sRGB", o, [&] {
      const auto planes = preprocess_raw(codes_to_unit(codes, 10), camera.raw);
      engine->reconstruct(planes.unsqueeze(0));  // as run_live (hw/live)
    });
    row.per_second = 1000.0 / row.median_ms;
  } else if (name == "simulator") {
    const auto camera = load_camera_config(default_camera_path());
    const auto rig = load_camera_rig(camera);
    const auto scene = torch::rand({3, kScene, kScene});
    auto gen = at::detail::createCPUGenerator(0);
    c10::InferenceMode guard;
    row = time_row(name, "one noisy raw capture of a 256x256 scene through the reference rig", o,
                   [&] { simulate_raw(rig, scene, true, gen); });
    row.per_second = 1000.0 / row.median_ms;
  } else if (name == "infer_paper") {
    row = infer_row(name, 128, o);
  } else if (name == "infer_cpu") {
    row = infer_row(name, 16, o);
  } else if (name == "train_paper") {
    row = train_row(name, 128, true, o);
  } else if (name == "train_cpu") {
    row = train_row(name, 16, false, o);
  } else if (name == "train_recipe") {
    row = train_recipe_row(name, o);
  } else if (name.rfind("peak_", 0) == 0 && name.size() > 5) {
    const auto names = peak_row_names();
    if (std::find(names.begin(), names.end(), name) == names.end())
      throw Error("bench: row '" + name + "' needs bf16, which this CPU does not run natively");
    row = peak_row(name, o);
  } else if (name == "mask_step") {
    row = mask_row(o);
  } else if (name == "loader") {
    const auto camera = load_camera_config(default_camera_path());
    auto rig = std::make_shared<const Rig>(load_camera_rig(camera));
    std::vector<std::filesystem::path> images;  // the golden scenes shipped with the tests
    for (const auto& p : list_images(data_dir() / "tests" / "data" / "golden", {".png"}))
      if (p.stem().string().find("_scene") != std::string::npos) images.push_back(p);
    auto source = std::make_shared<SimulatedPairs>(images, rig, camera, 0);
    LoaderOptions lo;
    lo.batch = 4;
    lo.workers = o.loader_workers;
    BatchLoader loader(source, lo);
    row = time_row(name,
                   "on-the-fly simulated batches of 4 (decode, resize, simulate, preprocess), " +
                       std::to_string(lo.workers) + " loader threads, consumer idle",
                   o, [&] { loader.next(); });
    row.per_second = 4000.0 / row.median_ms;  // samples per second
  } else {
    std::string names;
    for (const auto& n : bench_row_names()) names += " " + n;
    throw Error("bench: unknown row '" + name + "'; rows:" + names);
  }
  if (o.bf16 && bench_row_has_precision(name)) row.name += "_bf16";
  row.peak_rss_mb = peak_rss_mb();
  return row;
}

}  // namespace flatnet
