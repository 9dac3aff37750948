#include "train/mask_trainer.hpp"

#include "train/csv_log.hpp"
#include "train/loop.hpp"
#include "train/nonfinite.hpp"
#include "train/options.hpp"
#include "train/run_id.hpp"
#include "train/trainer_checkpoint.hpp"

#include <fstream>
#include <optional>
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

std::unique_ptr<torch::optim::Optimizer> make_optimizer(const std::vector<torch::Tensor>& params,
                                                        const MaskTrainOptions& o) {
  if (o.optimizer == "sgd")
    return std::make_unique<torch::optim::SGD>(params, torch::optim::SGDOptions(o.lr).momentum(o.momentum));
  if (o.optimizer == "adam") return std::make_unique<torch::optim::Adam>(params, torch::optim::AdamOptions(o.lr));
  throw Error("config: train.optimizer must be sgd or adam, got '" + o.optimizer + "'");
}

const char* const kMaskLogHeader = "step,loss,psnr,gamma,throughput";
const char* const kValHeader = "step,val_psnr,gamma,throughput";

}  // namespace

// The mask trainer in the shape of GanTrainer: its state as members, one method per hook of the
// one training loop (train/loop.hpp: step, log, checkpoint), set-up (a fresh or resumed run) and
// the outputs written at the end.
class MaskTrainer {
 public:
  MaskTrainer(MaskModel& model, const torch::Tensor& train_scenes, const torch::Tensor& val_scenes,
              const WienerCamera& cam, const MaskTrainOptions& o)
      : model_(model),
        train_(train_scenes),
        val_(val_scenes),
        cam_(cam),
        o_(o),
        checkpoint_path_(trainer_checkpoint_path(o.out)),
        rng_(o.seed),
        pick_(0, train_scenes.size(0) - 1) {
    // gamma > 0 by construction: it is learned as its logarithm.
    log_gamma_ = torch::tensor(std::log(o.gamma_init)).set_requires_grad(true);
    params_ = model_->parameters();
    params_.push_back(log_gamma_);
    opt_ = make_optimizer(params_, o);
    for (const auto& p : model_->named_parameters()) state_.params.emplace_back(p.key(), p.value());
    state_.params.emplace_back("log_gamma", log_gamma_);
    state_.optimizer = opt_.get();
    state_.optimizer_kind = o.optimizer;
    state_.format = "flatnet-mask-checkpoint";
    state_.size_hint = "another mask.rank or mask.elements?";
  }

  MaskTrainSummary run() {
    restore_or_start();
    loop_ = checkpointed_loop(
        o_, "mask", checkpoint_path_, first_step_, seconds_before_, [this](int64_t step) { step_once(step); },
        [this](int64_t done) { return log_row(done); }, [this](int64_t done) { checkpoint(done); });
    const auto r = loop_->run();
    if (r.last_step == first_step_ && o_.resume) score();  // a resumed run with no step left: its state's scores
    summary_.steps = r.last_step;
    summary_.seconds = loop_->trained_seconds();  // log.csv was flushed with each row
    write_outputs();
    return summary_;
  }

 private:
  // A fresh run (validated at step 0) or the state of OUT/latest.ckpt, with logs cut back to it.
  void restore_or_start() {
    if (o_.resume) {
      const auto restored = read_trainer_checkpoint(checkpoint_path_, state_);
      first_step_ = restored.step;
      seconds_before_ = restored.seconds;
      std::istringstream rng_state(restored.file.meta("rng", checkpoint_path_));
      rng_state >> rng_;  // the data order
      require(!rng_state.fail(), checkpoint_path_, "rng is not the state of the data order's generator");
      state_.run_id = restored.run_id;
    }
    state_.run_id = settle_run_id(o_.out, o_.resume, state_.run_id, checkpoint_path_, o_.force);
    const auto log_file = o_.out / "log.csv", val_file = o_.out / "val.csv";
    log_ = o_.resume ? CsvLog::resume(log_file, kMaskLogHeader, first_step_) : CsvLog(log_file, kMaskLogHeader);
    val_log_ = o_.resume ? CsvLog::resume(val_file, kValHeader, first_step_) : CsvLog(val_file, kValHeader);
    add_rows(train_curve_, *log_, 2);  // a resumed run's rows up to its checkpoint (none for a new run)
    add_rows(val_curve_, *val_log_, 1);
    if (!o_.resume) validate(0);
  }

  // One optimiser step, or none when the loss or its gradient is not finite (train/nonfinite.hpp).
  void step_once(int64_t step) {
    std::vector<int64_t> idx(o_.batch);
    for (auto& i : idx) i = pick_(rng_);
    const auto x = train_.index_select(0, torch::tensor(idx));
    auto gen = at::detail::createCPUGenerator(o_.seed * 7919ULL + static_cast<uint64_t>(step));
    const auto P = psf_spectrum(model_->window());
    const auto rec = wiener(capture(x, P, cam_, gen), P, log_gamma_.exp(), cam_);
    const auto loss = torch::mse_loss(rec, x);
    const double value = loss.item<double>();
    if (!std::isfinite(value)) throw NonFiniteStep("loss", value, step);
    opt_->zero_grad();
    loss.backward();
    std::vector<torch::Tensor> grads;
    for (const auto& p : params_) grads.push_back(p.grad());
    if (!all_finite(grads)) throw NonFiniteStep("loss's gradient", std::nan(""), step);
    opt_->step();
    sum_loss_ += value;
    sum_psnr_ += psnr_sum(rec.detach(), x) / o_.batch;
    ++count_;
  }

  std::string log_row(int64_t done) {
    if (count_ == 0) return "every step since the last log was skipped";
    const double g = std::exp(log_gamma_.item<double>());
    log_->add(done, sum_loss_ / count_, sum_psnr_ / count_, g, throughput(model_->window().detach()));
    train_curve_.x.push_back(static_cast<double>(done));
    train_curve_.y.push_back(sum_psnr_ / count_);
    log_->flush();
    std::ostringstream st;
    st << "psnr " << std::fixed << std::setprecision(2) << sum_psnr_ / count_ << " gamma " << std::scientific
       << std::setprecision(2) << g;
    sum_loss_ = sum_psnr_ = 0;
    count_ = 0;
    return st.str();
  }

  void score() {
    torch::NoGradGuard ng;
    const auto w = model_->window();
    const double g = std::exp(log_gamma_.item<double>());
    summary_.val_psnr = mask_psnr(w, g, val_, cam_, 12345);
    summary_.gamma = g;
    summary_.throughput = throughput(w);
  }

  void validate(int64_t step) {
    score();
    val_log_->add(step, summary_.val_psnr, summary_.gamma, summary_.throughput);
    val_log_->flush();
    val_curve_.x.push_back(static_cast<double>(step));
    val_curve_.y.push_back(summary_.val_psnr);
  }

  void checkpoint(int64_t done) {
    validate(done);
    std::ostringstream rng_state;
    rng_state << rng_;
    write_trainer_checkpoint(checkpoint_path_, state_, done, loop_->trained_seconds(), {{"rng", rng_state.str()}});
  }

  // mask.png, vectors.mat, gamma.txt and curve.png.
  void write_outputs() {
    torch::NoGradGuard ng;
    write_mask_png(o_.out / "mask.png", model_->window());
    write_mat(o_.out / "vectors.mat",
              {{"U", model_->U.detach().to(torch::kFloat64)}, {"V", model_->V.detach().to(torch::kFloat64)}});
    std::ostringstream gs;
    gs << std::setprecision(9) << summary_.gamma << "\n";
    write_text_atomically(o_.out / "gamma.txt", gs.str());
    PlotOptions po;
    po.title = "mask training (rank " + std::to_string(model_->options().rank) + ")";
    po.xlabel = "step";
    po.ylabel = "PSNR dB";
    write_line_plot(o_.out / "curve.png", {train_curve_, val_curve_}, po);
  }

  MaskModel& model_;
  const torch::Tensor& train_;
  const torch::Tensor& val_;
  const WienerCamera& cam_;
  const MaskTrainOptions& o_;
  const std::filesystem::path checkpoint_path_;
  torch::Tensor log_gamma_;
  std::vector<torch::Tensor> params_;
  std::unique_ptr<torch::optim::Optimizer> opt_;
  TrainerState state_;
  std::mt19937_64 rng_;
  std::uniform_int_distribution<int64_t> pick_;
  int64_t first_step_ = 0;
  double seconds_before_ = 0;
  std::optional<CsvLog> log_, val_log_;
  Series train_curve_{"train (batch)", {}, {}}, val_curve_{"validation", {}, {}};
  double sum_loss_ = 0, sum_psnr_ = 0;
  int64_t count_ = 0;
  MaskTrainSummary summary_;
  std::unique_ptr<TrainingLoop> loop_;
};

MaskTrainSummary train_mask(MaskModel& model, const torch::Tensor& train_scenes, const torch::Tensor& val_scenes,
                            const WienerCamera& cam, const MaskTrainOptions& o) {
  require(cam.noise_sigma > 0 || cam.photons > 0, "camera.noise_sigma",
          "must be positive (a noise-free design is degenerate)");
  require(train_scenes.size(0) > 0 && val_scenes.size(0) > 0, key_of(photo_split_fields(), &PhotoSplit::images),
          "no training or validation images");
  std::filesystem::create_directories(o.out);
  return MaskTrainer(model, train_scenes, val_scenes, cam, o).run();
}

}  // namespace flatnet
