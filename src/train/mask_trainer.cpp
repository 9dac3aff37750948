#include "train/mask_trainer.hpp"

#include "train/csv_log.hpp"
#include "train/loop.hpp"
#include "train/nonfinite.hpp"
#include "train/run_id.hpp"
#include "train/trainer_checkpoint.hpp"

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

namespace flatnet {

void write_mask_png(const std::filesystem::path& path, const torch::Tensor& window) {
  write_gray16(path, torch::round(window.detach().clamp(0, 1) * 65535.0).to(torch::kInt32));
}

namespace {

// A resumed run's curve: the rows its log kept.
void add_rows(Series& curve, const CsvLog& log, size_t column) {
  for (const auto& [x, y] : log.column(column)) curve.x.push_back(x), curve.y.push_back(y);
}

}  // namespace

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
  TrainerState state;
  for (const auto& p : model->named_parameters()) state.params.emplace_back(p.key(), p.value());
  state.params.emplace_back("log_gamma", log_gamma);
  state.optimizer = opt.get(), state.optimizer_kind = o.optimizer;
  state.format = "flatnet-mask-checkpoint", state.size_hint = "another mask.rank or mask.elements?";
  const auto checkpoint = trainer_checkpoint_path(o.out);
  int64_t first_step = 0;
  double seconds_before = 0;
  if (o.resume) {
    const auto restored = read_trainer_checkpoint(checkpoint, state);
    first_step = restored.step, seconds_before = restored.seconds;
    std::istringstream rng_state(restored.file.meta("rng", checkpoint));
    rng_state >> rng;  // the data order
    require(!rng_state.fail(), checkpoint, "rng is not the state of the data order's generator");
    state.run_id = restored.run_id;
  }
  state.run_id = settle_run_id(o.out, o.resume, state.run_id, checkpoint, o.force);
  const char* log_header = "step,loss,psnr,gamma,throughput";
  const char* val_header = "step,val_psnr,gamma,throughput";
  CsvLog log = o.resume ? CsvLog::resume(o.out / "log.csv", log_header, first_step) : CsvLog(o.out / "log.csv", log_header);
  CsvLog val_log =
      o.resume ? CsvLog::resume(o.out / "val.csv", val_header, first_step) : CsvLog(o.out / "val.csv", val_header);
  Series train_curve{"train (batch)", {}, {}}, val_curve{"validation", {}, {}};
  add_rows(train_curve, log, 2);  // a resumed run's rows up to its checkpoint (none for a new run)
  add_rows(val_curve, val_log, 1);
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

  auto lo = loop_schedule(o, "mask", "the last checkpoint (" + checkpoint.string() + ")");
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
    std::ostringstream rng_state;
    rng_state << rng;
    write_trainer_checkpoint(checkpoint, state, done, loop->trained_seconds(), {{"rng", rng_state.str()}});
  };
  loop = std::make_unique<TrainingLoop>(lo, hooks);
  const auto r = loop->run();
  if (r.last_step == first_step && o.resume) score();  // a resumed run with no step left: its state's scores
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
