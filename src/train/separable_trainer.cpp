#include "train/separable_trainer.hpp"

#include <cmath>
#include <iostream>
#include <iomanip>
#include <optional>
#include <sstream>
#include <thread>

#include "core/error.hpp"
#include "core/util.hpp"
#include "nn/optimizer_state.hpp"
#include "eval/plot.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "optics/separable_camera.hpp"
#include "optics/simulator.hpp"
#include "eval/mask_score.hpp"
#include "train/csv_log.hpp"
#include "train/loop.hpp"
#include "train/mask_trainer.hpp"
#include "train/nonfinite.hpp"
#include "train/run_id.hpp"
#include "train/trainer_checkpoint.hpp"

namespace flatnet {

namespace {

constexpr int kChannel = 1;                                  // gb: the channel FlatNet's transpose init uses
constexpr int64_t kTop = 6, kLeft = 10, kH = 500, kW = 620;  // the reference camera's window
const int64_t kScene = SeparableCameraOptions{}.scene;       // its scene side (256)

torch::Tensor centre_columns(const torch::Tensor& m) { return m - m.mean(0, true); }  // C_n m

// Linear-light scenes {B,N,N} -> Tikhonov reconstructions {B,N,N} through the separable camera of
// (u, v). `noise_gen` draws the sensor noise (training: fresh; validation: fixed).
torch::Tensor capture_and_reconstruct(const torch::Tensor& u, const torch::Tensor& v, const torch::Tensor& lambda,
                                      const torch::Tensor& X, at::Generator& noise_gen) {
  const auto rig = separable_rig(u, v);
  const auto L = rig.phil[kChannel], R = rig.phir[kChannel], g = rig.gain[kChannel];
  // Expected signal on the whole plane: gain (PhiL X PhiR^T + the open mask's pedestal), + dark.
  auto S =
      g * (torch::matmul(torch::matmul(L, X), R.t()) + torch::outer(rig.vig_rows, rig.vig_cols) * X.sum({1, 2}, true)) +
      rig.dark;
  // Shot noise (Gaussian approximation of Poisson, reparameterised) and read noise, full-scale units.
  const auto e1 = at::normal(0.0, 1.0, S.sizes(), noise_gen, S.options());
  const auto e2 = at::normal(0.0, 1.0, S.sizes(), noise_gen, S.options());
  S = S + torch::sqrt(S.clamp_min(0) / rig.full_well + 1e-12) * e1 + (rig.read_noise / rig.full_well) * e2;
  auto Y = S.slice(1, kTop, kTop + kH).slice(2, kLeft, kLeft + kW);
  Y = Y - Y.mean(1, true) - Y.mean(2, true) + Y.mean({1, 2}, true);  // double centring
  // The exact calibration of this camera: centred windows of sqrt(gain) Phi.
  const auto P = centre_columns(L.slice(0, kTop, kTop + kH)) * torch::sqrt(g);
  const auto Q = centre_columns(R.slice(0, kLeft, kLeft + kW)) * torch::sqrt(g);
  auto [UL, sL, VLt] = torch::linalg::svd(P, false, c10::nullopt);
  auto [UR, sR, VRt] = torch::linalg::svd(Q, false, c10::nullopt);
  const auto s = sL.unsqueeze(1) * sR.unsqueeze(0);  // eq. 2.6's filter
  const auto filter = s / (s * s + lambda);
  const auto core = torch::matmul(torch::matmul(UL.t(), Y), UR) * filter;
  return torch::matmul(torch::matmul(VLt.t(), core), VRt);
}

double mean_psnr(const torch::Tensor& rec, const torch::Tensor& truth) {
  const auto mse = (rec.clamp(0, 1) - truth).pow(2).mean({1, 2}).clamp_min(1e-12);
  return (-10.0 * torch::log10(mse)).mean().item<double>();
}

std::pair<torch::Tensor, torch::Tensor> read_codes(const std::filesystem::path& path) {
  const auto codes = load_code_pair(path);
  return {codes.rows.to(torch::kFloat32), codes.cols.to(torch::kFloat32)};
}

}  // namespace

double separable_psnr(const torch::Tensor& u, const torch::Tensor& v, double lambda, const torch::Tensor& scenes,
                      uint64_t seed) {
  torch::NoGradGuard no_grad;
  auto gen = at::detail::createCPUGenerator(seed);
  const auto X = srgb_to_linear(scenes);
  double sum = 0;
  for (int64_t i = 0; i < X.size(0); i += 8) {
    const auto batch = X.slice(0, i, std::min(X.size(0), i + 8));
    const auto rec =
        capture_and_reconstruct(u.to(torch::kFloat32), v.to(torch::kFloat32), torch::tensor(lambda), batch, gen);
    sum += mean_psnr(rec, batch) * batch.size(0);
  }
  return sum / X.size(0);
}

namespace {

const char* const kSeparableLogHeader = "step,loss,throughput,lambda,val_psnr";

// The photographs of the split as luma scenes {B,N,N} in sRGB: training (up to train_limit) and
// validation (up to val_count).
std::pair<torch::Tensor, torch::Tensor> load_scenes(const SeparableTrainOptions& o) {
  const auto [train_files, val_files] = split_image_files(o.images, o.val_fraction, o.split_seed);
  auto train_list = train_files;
  if (o.train_limit > 0 && static_cast<int64_t>(train_list.size()) > o.train_limit) train_list.resize(o.train_limit);
  auto val_list = val_files;
  if (static_cast<int64_t>(val_list.size()) > o.val_count) val_list.resize(o.val_count);
  const int workers = all_cores();
  return {load_luma_scenes(train_list, kScene, workers), load_luma_scenes(val_list, kScene, workers)};
}

// The codes' pre-activations (u = tanh(a)) to start from: o.init_codes, else random (seeded).
std::pair<torch::Tensor, torch::Tensor> initial_preactivations(const SeparableTrainOptions& o) {
  torch::manual_seed(o.seed);
  if (!o.init_codes.empty()) {
    const auto [u0, v0] = read_codes(o.init_codes);
    return {torch::atanh(u0.clamp(-0.95, 0.95)), torch::atanh(v0.clamp(-0.95, 0.95))};
  }
  auto a = torch::randn({o.code_length}) * 0.5;
  auto b = torch::randn({o.code_length}) * 0.5;
  return {a, b};
}

}  // namespace

// The code-pair trainer in the shape of GanTrainer: its state as members, one method per hook of
// the one training loop (train/loop.hpp), set-up (a fresh or resumed run) and the outputs at the end.
class SeparableTrainer {
 public:
  explicit SeparableTrainer(const SeparableTrainOptions& o) : o_(o), checkpoint_path_(trainer_checkpoint_path(o.out)) {
    std::tie(train_, val_) = load_scenes(o);
    train_linear_ = srgb_to_linear(train_);
    std::tie(a_, b_) = initial_preactivations(o);
    a_.requires_grad_();
    b_.requires_grad_();
    log_lambda_ = torch::tensor(std::log(o.lambda_init)).requires_grad_();
    opt_ = std::make_unique<torch::optim::Adam>(std::vector<torch::Tensor>{a_, b_, log_lambda_},
                                                torch::optim::AdamOptions(o.lr));
    std::filesystem::create_directories(o.out);
    gen_ = at::detail::createCPUGenerator(o.seed + 1);
    state_.params = {{"a", a_}, {"b", b_}, {"log_lambda", log_lambda_}};
    state_.optimizer = opt_.get();
    state_.optimizer_kind = "adam";
    state_.format = "flatnet-codes-checkpoint";
    state_.size_hint = "another codes.length or codes.init?";
  }

  SeparableTrainSummary run() {
    restore_or_start();
    loop_ = checkpointed_loop(
        o_, "codes", checkpoint_path_, first_step_, seconds_before_, [this](int64_t step) { step_once(step); },
        [this](int64_t done) { return log_row(done); }, [this](int64_t done) { checkpoint(done); });
    const auto r = loop_->run();
    finish(r);
    return summary_;
  }

 private:
  std::pair<torch::Tensor, torch::Tensor> codes() const {
    auto u = torch::tanh(a_), v = torch::tanh(b_);
    if (o_.binary) u = straight_through_sign(u), v = straight_through_sign(v);
    return {u, v};
  }

  double lambda() const { return std::exp(log_lambda_.item<double>()); }

  double val_psnr() const {
    const auto [u, v] = codes();
    return separable_psnr(u.detach(), v.detach(), lambda(), val_, 99);
  }

  // A fresh run (scored at the start) or the state of OUT/latest.ckpt, with the log cut back to it.
  void restore_or_start() {
    if (o_.resume) {
      const auto restored = read_trainer_checkpoint(checkpoint_path_, state_);
      first_step_ = restored.step;
      seconds_before_ = restored.seconds;
      // The data order's and the noise's generator, checked before LibTorch reads it.
      const auto* rng = restored.file.find("rng");
      require(rng != nullptr, checkpoint_path_, "lacks 'rng', the state of the data and noise generator");
      require_cpu_generator_state(*rng, checkpoint_path_, "rng");
      gen_.set_state(*rng);
      const auto start = restored.file.meta("val_psnr_start", checkpoint_path_);
      require(is_decimal_number(start), checkpoint_path_,
              "val_psnr_start '" + start.substr(0, 40) + "' is not a number");
      summary_.val_psnr_start = std::strtod(start.c_str(), nullptr);
      state_.run_id = restored.run_id;
    } else {
      summary_.val_psnr_start = val_psnr();
      std::cerr << "separable codes: validation PSNR at the start " << summary_.val_psnr_start << " dB\n";
    }
    state_.run_id = settle_run_id(o_.out, o_.resume, state_.run_id, checkpoint_path_, o_.force);
    const auto file = o_.out / "log.csv";
    log_ = o_.resume ? CsvLog::resume(file, kSeparableLogHeader, first_step_) : CsvLog(file, kSeparableLogHeader);
    for (const auto& [x, loss] : log_->column(1))  // a resumed run's rows up to its checkpoint (none for a new run)
      train_curve_.x.push_back(x), train_curve_.y.push_back(-10 * std::log10(std::max(1e-12, loss)));
    for (const auto& [x, psnr] : log_->column(4)) val_curve_.x.push_back(x), val_curve_.y.push_back(psnr);
  }

  void step_once(int64_t step) {
    const auto idx = torch::randint(train_linear_.size(0), {o_.batch}, gen_, torch::kLong);
    const auto X = train_linear_.index_select(0, idx);
    const auto [u, v] = codes();
    const auto rec = capture_and_reconstruct(u, v, torch::exp(log_lambda_), X, gen_);
    const auto t = code_throughput(u, v);
    const auto loss = (rec - X).pow(2).mean() + throughput_penalty(t, o_.target_throughput, o_.throughput_tolerance);
    last_loss_ = loss.item<double>();
    last_throughput_ = t.item<double>();
    opt_->zero_grad();
    loss.backward();
    // An SVD with nearly equal singular values can give a non-finite gradient: that step is
    // skipped, and kNonFiniteLimit in a row stop (train/nonfinite.hpp).
    if (!std::isfinite(last_loss_)) throw NonFiniteStep("loss", last_loss_, step + 1);
    if (!all_finite({a_.grad(), b_.grad(), log_lambda_.grad()}))
      throw NonFiniteStep("gradient of the codes or lambda", std::nan(""), step + 1);
    opt_->step();
  }

  void checkpoint(int64_t done) {
    last_val_ = summary_.val_psnr = val_psnr();
    val_curve_.x.push_back(static_cast<double>(done));
    val_curve_.y.push_back(last_val_);
    std::ostringstream start;
    start << std::setprecision(17) << summary_.val_psnr_start;
    write_trainer_checkpoint(checkpoint_path_, state_, done, loop_->trained_seconds(),
                             {{"val_psnr_start", start.str()}}, {{"rng", gen_.get_state()}});
  }

  std::string log_row(int64_t done) {
    train_curve_.x.push_back(static_cast<double>(done));
    train_curve_.y.push_back(-10 * std::log10(std::max(1e-12, last_loss_)));
    log_->add(done, last_loss_, last_throughput_, lambda(), last_val_);
    if (!std::isnan(last_val_)) log_->flush();  // the log on disk at each validation (CsvLog), and at the end
    last_val_ = std::nan("");
    return "loss " + std::to_string(last_loss_) + " t " + std::to_string(last_throughput_);
  }

  // The summary, codes.mat, lambda.txt, the log and curve.png.
  void finish(const LoopResult& r) {
    summary_.steps = r.last_step;
    const auto [u, v] = codes();
    summary_.lambda = lambda();
    summary_.throughput = code_throughput(u, v).item<double>();
    summary_.seconds = loop_->trained_seconds();
    if (r.last_step == first_step_ && o_.resume)  // a resumed run with no step left: its state's score
      summary_.val_psnr = separable_psnr(u.detach(), v.detach(), summary_.lambda, val_, 99);
    save_code_pair(o_.out / "codes.mat", u, v);
    write_text_atomically(o_.out / "lambda.txt", std::to_string(summary_.lambda) + "\n");
    log_->flush();
    PlotOptions po;
    po.title = "separable codes: PSNR (Tikhonov, linear light)";
    po.xlabel = "step";
    po.ylabel = "PSNR dB";
    write_line_plot(o_.out / "curve.png", {train_curve_, val_curve_}, po);
  }

  const SeparableTrainOptions& o_;
  const std::filesystem::path checkpoint_path_;
  torch::Tensor train_, val_, train_linear_;
  torch::Tensor a_, b_, log_lambda_;  // pre-activations of the codes, and lambda's logarithm
  std::unique_ptr<torch::optim::Adam> opt_;
  at::Generator gen_;
  TrainerState state_;
  SeparableTrainSummary summary_;
  int64_t first_step_ = 0;
  double seconds_before_ = 0;
  std::optional<CsvLog> log_;
  Series train_curve_{"train (batch)", {}, {}}, val_curve_{"validation", {}, {}};
  double last_loss_ = 0, last_throughput_ = 0, last_val_ = std::nan("");
  std::unique_ptr<TrainingLoop> loop_;
};

SeparableTrainSummary train_separable_codes(const SeparableTrainOptions& o) {
  require(o.iterations >= 1 && o.batch >= 1, "separable training", "iterations and batch must be positive");
  require(!o.out.empty(), "separable training", "an output folder is needed");
  return SeparableTrainer(o).run();
}

}  // namespace flatnet
