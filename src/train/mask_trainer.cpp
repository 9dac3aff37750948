#include "train/mask_trainer.hpp"

#include "train/csv_log.hpp"
#include "train/loop.hpp"
#include "train/nonfinite.hpp"

#include <fstream>
#include <iomanip>
#include <random>
#include <thread>

#include "core/error.hpp"
#include "core/util.hpp"
#include "eval/mask_score.hpp"
#include "eval/metrics.hpp"
#include "eval/plot.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "io/safetensors.hpp"

namespace flatnet {

void write_mask_png(const std::filesystem::path& path, const torch::Tensor& window) {
  write_gray16(path, torch::round(window.detach().clamp(0, 1) * 65535.0).to(torch::kInt32));
}

namespace {

constexpr const char* kMaskCheckpointFormat = "flatnet-mask-checkpoint";

std::filesystem::path checkpoint_path(const std::filesystem::path& out) { return out / "latest.ckpt"; }

std::string state_key(const torch::Tensor& p) { return c10::guts::to_string(p.unsafeGetTensorImpl()); }

// What a run needs to continue: the parameters (the model's, then log gamma), the optimiser's
// state per parameter (by its index in `params`: LibTorch keys it by address), the step, the
// seconds trained and the data order's generator.
struct MaskRunState {
  std::vector<torch::Tensor>& params;
  std::vector<std::string> names;  // of `params`
  torch::optim::Optimizer& opt;
  const std::string& optimizer;  // sgd | adam
  std::mt19937_64& rng;
};

void write_mask_checkpoint(const std::filesystem::path& path, const MaskRunState& run, int64_t step, double seconds) {
  std::vector<std::pair<std::string, torch::Tensor>> tensors;
  for (size_t i = 0; i < run.params.size(); ++i) {
    tensors.emplace_back("param." + run.names[i], run.params[i].detach());
    const auto it = run.opt.state().find(state_key(run.params[i]));
    if (it == run.opt.state().end()) continue;  // no step taken yet
    const auto base = "optimizer." + run.names[i] + ".";
    if (run.optimizer == "sgd") {
      const auto& st = static_cast<const torch::optim::SGDParamState&>(*it->second);
      if (st.momentum_buffer().defined()) tensors.emplace_back(base + "momentum_buffer", st.momentum_buffer());
    } else {
      const auto& st = static_cast<const torch::optim::AdamParamState&>(*it->second);
      tensors.emplace_back(base + "step", torch::tensor(st.step(), torch::kInt64));
      tensors.emplace_back(base + "exp_avg", st.exp_avg());
      tensors.emplace_back(base + "exp_avg_sq", st.exp_avg_sq());
    }
  }
  std::ostringstream rng_state, secs;
  rng_state << run.rng;
  secs << std::setprecision(17) << seconds;
  write_safetensors(path, tensors,
                    {{"format", kMaskCheckpointFormat},
                     {"step", std::to_string(step)},
                     {"train_seconds", secs.str()},
                     {"optimizer", run.optimizer},
                     {"rng", rng_state.str()}});
}

// The stored tensor `name`, shaped like `like` and finite, or an Error naming the checkpoint.
torch::Tensor stored_like(const SafeTensors& st, const std::string& name, const torch::Tensor& like,
                          const std::filesystem::path& path) {
  const auto* t = st.find(name);
  require(t != nullptr, path, "lacks '" + name + "' (not a checkpoint of this mask trainer?)");
  require(t->sizes() == like.sizes(), path,
          "'" + name + "' is " + c10::str(t->sizes()) + ", this run's " + c10::str(like.sizes()) +
              " (another mask.rank or mask.elements?)");
  require(t->is_floating_point() && torch::isfinite(*t).all().item<bool>(), path,
          "'" + name + "' holds NaN or infinity, or is not a floating-point tensor");
  return t->to(like.scalar_type()).clone();
}

// Restores `run` from the checkpoint; returns {step, seconds trained}.
std::pair<int64_t, double> read_mask_checkpoint(const std::filesystem::path& path, const MaskRunState& run) {
  const auto st = read_safetensors(path);
  require(st.meta("format", path) == kMaskCheckpointFormat, path,
          "is not a mask training checkpoint (format '" + st.meta("format", path) + "')");
  const auto& optimizer = st.meta("optimizer", path);
  require(optimizer == run.optimizer, path,
          "the run trained with train.optimizer " + optimizer + "; it cannot change to " + run.optimizer + " on resume");
  const auto& step_text = st.meta("step", path);
  const auto& seconds_text = st.meta("train_seconds", path);
  require(is_decimal_number(step_text) && step_text.find_first_of(".eE-") == std::string::npos &&
              step_text.size() <= 12,
          path, "step '" + step_text.substr(0, 40) + "' is not a step count");
  require(is_decimal_number(seconds_text) && std::strtod(seconds_text.c_str(), nullptr) >= 0, path,
          "train_seconds '" + seconds_text.substr(0, 40) + "' is not a duration");
  std::istringstream rng_state(st.meta("rng", path));
  rng_state >> run.rng;
  require(!rng_state.fail(), path, "rng is not the state of the data order's generator");
  torch::NoGradGuard ng;
  for (size_t i = 0; i < run.params.size(); ++i) {
    const auto& p = run.params[i];
    p.copy_(stored_like(st, "param." + run.names[i], p, path));
    const auto base = "optimizer." + run.names[i] + ".";
    run.opt.state().erase(state_key(p));
    if (run.optimizer == "sgd") {
      if (!st.find(base + "momentum_buffer")) continue;
      auto state = std::make_unique<torch::optim::SGDParamState>();
      state->momentum_buffer(stored_like(st, base + "momentum_buffer", p, path));
      run.opt.state()[state_key(p)] = std::move(state);
    } else {
      const auto* step = st.find(base + "step");
      if (!step) continue;
      require(step->numel() == 1 && step->scalar_type() == torch::kInt64 && step->item<int64_t>() >= 0, path,
              "'" + base + "step' is not one non-negative integer");
      auto state = std::make_unique<torch::optim::AdamParamState>();
      state->step(step->item<int64_t>());
      state->exp_avg(stored_like(st, base + "exp_avg", p, path));
      state->exp_avg_sq(stored_like(st, base + "exp_avg_sq", p, path));
      run.opt.state()[state_key(p)] = std::move(state);
    }
  }
  return {std::stoll(step_text), std::strtod(seconds_text.c_str(), nullptr)};
}

// A curve from a log's kept rows: its first column against column `column`.
void add_rows(Series& curve, const std::filesystem::path& csv, size_t column) {
  std::ifstream in(csv);
  std::string line;
  std::getline(in, line);  // the header
  while (std::getline(in, line)) {
    std::vector<std::string> fields;
    std::stringstream ss(line);
    for (std::string f; std::getline(ss, f, ',');) fields.push_back(f);
    if (fields.size() <= column || !is_decimal_number(fields[0]) || !is_decimal_number(fields[column])) continue;
    curve.x.push_back(std::strtod(fields[0].c_str(), nullptr));
    curve.y.push_back(std::strtod(fields[column].c_str(), nullptr));
  }
}

}  // namespace

bool has_mask_checkpoint(const std::filesystem::path& out) { return std::filesystem::exists(checkpoint_path(out)); }

MaskTrainSummary train_mask(MaskModel& model, const torch::Tensor& train_scenes, const torch::Tensor& val_scenes,
                            const WienerCamera& cam, const MaskTrainOptions& o) {
  require(cam.noise_sigma > 0 || cam.photons > 0, "camera.noise_sigma",
          "must be positive (a noise-free design is degenerate)");
  require(train_scenes.size(0) > 0 && val_scenes.size(0) > 0, "data.images", "no training or validation images");
  std::filesystem::create_directories(o.out);
  // gamma > 0 by construction: it is learned as its logarithm.
  auto log_gamma = torch::tensor(std::log(o.gamma_init)).set_requires_grad(true);
  std::vector<torch::Tensor> params = model->parameters();
  params.push_back(log_gamma);
  std::unique_ptr<torch::optim::Optimizer> opt;
  if (o.optimizer == "sgd")
    opt = std::make_unique<torch::optim::SGD>(params, torch::optim::SGDOptions(o.lr).momentum(o.momentum));
  else if (o.optimizer == "adam")
    opt = std::make_unique<torch::optim::Adam>(params, torch::optim::AdamOptions(o.lr));
  else
    throw Error("config: train.optimizer must be sgd or adam, got '" + o.optimizer + "'");

  const auto n = train_scenes.size(0);
  std::mt19937_64 rng(o.seed);
  std::vector<std::string> names;
  for (const auto& p : model->named_parameters()) names.push_back(p.key());
  names.push_back("log_gamma");
  const MaskRunState run{params, names, *opt, o.optimizer, rng};
  int64_t first_step = 0;
  double seconds_before = 0;
  if (o.resume) {
    require(has_mask_checkpoint(o.out), checkpoint_path(o.out), "nothing to resume (no checkpoint)");
    std::tie(first_step, seconds_before) = read_mask_checkpoint(checkpoint_path(o.out), run);
  }
  const char* log_header = "step,loss,psnr,gamma,throughput";
  const char* val_header = "step,val_psnr,gamma,throughput";
  CsvLog log = o.resume ? CsvLog::resume(o.out / "log.csv", log_header, first_step) : CsvLog(o.out / "log.csv", log_header);
  CsvLog val_log =
      o.resume ? CsvLog::resume(o.out / "val.csv", val_header, first_step) : CsvLog(o.out / "val.csv", val_header);
  Series train_curve{"train (batch)", {}, {}}, val_curve{"validation", {}, {}};
  if (o.resume) {
    log.flush(), val_log.flush();
    add_rows(train_curve, log.path(), 2);
    add_rows(val_curve, val_log.path(), 1);
  }
  std::uniform_int_distribution<int64_t> pick(0, n - 1);
  double sum_loss = 0, sum_psnr = 0;
  int64_t count = 0;
  MaskTrainSummary s;
  auto score = [&]() {
    torch::NoGradGuard ng;
    const auto w = model->window();
    const double g = std::exp(log_gamma.item<double>());
    s.val_psnr = mask_psnr(w, g, val_scenes, cam, 12345), s.gamma = g, s.throughput = throughput(w);
  };
  auto validate = [&](int64_t step) {
    score();
    val_log.add(step, s.val_psnr, s.gamma, s.throughput);
    val_log.flush();
    val_curve.x.push_back(static_cast<double>(step));
    val_curve.y.push_back(s.val_psnr);
  };
  if (!o.resume) validate(0);
  else score();  // the resumed state's, for a run that takes no more steps

  auto lo = loop_schedule(o, "mask", "the last checkpoint (" + checkpoint_path(o.out).string() + ")");
  lo.first_step = first_step;
  lo.seconds_before = seconds_before;
  std::unique_ptr<TrainingLoop> loop;

  LoopHooks hooks;
  // One optimiser step, or none when the loss or its gradient is not finite (train/nonfinite.hpp).
  hooks.step = [&](int64_t step) {
    std::vector<int64_t> idx(o.batch);
    for (auto& i : idx) i = pick(rng);
    const auto x = train_scenes.index_select(0, torch::tensor(idx));
    auto gen = at::detail::createCPUGenerator(o.seed * 7919ULL + static_cast<uint64_t>(step));
    const auto P = psf_spectrum(model->window());
    const auto rec = wiener(capture(x, P, cam, gen), P, log_gamma.exp(), cam);
    const auto loss = torch::mse_loss(rec, x);
    const double value = loss.item<double>();
    if (!std::isfinite(value)) throw NonFiniteStep("loss", value, step);
    opt->zero_grad();
    loss.backward();
    std::vector<torch::Tensor> grads;
    for (const auto& p : params) grads.push_back(p.grad());
    if (!all_finite(grads)) throw NonFiniteStep("loss's gradient", std::nan(""), step);
    opt->step();
    sum_loss += value;
    sum_psnr += psnr_sum(rec.detach(), x) / o.batch;
    ++count;
  };
  hooks.log = [&](int64_t done) -> std::string {
    if (count == 0) return "every step since the last log was skipped";
    const double g = std::exp(log_gamma.item<double>());
    log.add(done, sum_loss / count, sum_psnr / count, g, throughput(model->window().detach()));
    train_curve.x.push_back(static_cast<double>(done));
    train_curve.y.push_back(sum_psnr / count);
    log.flush();
    std::ostringstream st;
    st << "psnr " << std::fixed << std::setprecision(2) << sum_psnr / count << " gamma " << std::scientific
       << std::setprecision(2) << g;
    sum_loss = sum_psnr = 0;
    count = 0;
    return st.str();
  };
  hooks.checkpoint = [&](int64_t done) {
    validate(done);
    write_mask_checkpoint(checkpoint_path(o.out), run, done, loop->trained_seconds());
  };
  loop = std::make_unique<TrainingLoop>(lo, hooks);
  const auto r = loop->run();
  s.steps = r.last_step;
  s.seconds = loop->trained_seconds();  // log.csv was flushed with each row

  torch::NoGradGuard ng;
  const auto window = model->window();
  write_mask_png(o.out / "mask.png", window);
  write_mat(o.out / "vectors.mat",
            {{"U", model->U.detach().to(torch::kFloat64)}, {"V", model->V.detach().to(torch::kFloat64)}});
  std::ostringstream gs;
  gs << std::setprecision(9) << s.gamma << "\n";
  write_text_atomically(o.out / "gamma.txt", gs.str());
  PlotOptions po;
  po.title = "mask training (rank " + std::to_string(model->options().rank) + ")";
  po.xlabel = "step";
  po.ylabel = "PSNR dB";
  write_line_plot(o.out / "curve.png", {train_curve, val_curve}, po);
  return s;
}

}  // namespace flatnet
