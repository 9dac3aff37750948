#include "train/separable_trainer.hpp"

#include <cmath>
#include <iostream>
#include <iomanip>
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

SeparableTrainSummary train_separable_codes(const SeparableTrainOptions& o) {
  require(o.iterations >= 1 && o.batch >= 1, "separable training", "iterations and batch must be positive");
  require(!o.out.empty(), "separable training", "an output folder is needed");
  const auto [train_files, val_files] = split_image_files(o.images, o.val_fraction, o.split_seed);
  auto train_list = train_files;
  if (o.train_limit > 0 && static_cast<int64_t>(train_list.size()) > o.train_limit) train_list.resize(o.train_limit);
  auto val_list = val_files;
  if (static_cast<int64_t>(val_list.size()) > o.val_count) val_list.resize(o.val_count);
  const int workers = all_cores();
  const auto train = load_luma_scenes(train_list, kScene, workers), val = load_luma_scenes(val_list, kScene, workers);
  const auto train_linear = srgb_to_linear(train);

  torch::manual_seed(o.seed);
  torch::Tensor a, b;  // pre-activations: u = tanh(a)
  if (!o.init_codes.empty()) {
    const auto [u0, v0] = read_codes(o.init_codes);
    a = torch::atanh(u0.clamp(-0.95, 0.95));
    b = torch::atanh(v0.clamp(-0.95, 0.95));
  } else {
    a = torch::randn({o.code_length}) * 0.5;
    b = torch::randn({o.code_length}) * 0.5;
  }
  a.requires_grad_();
  b.requires_grad_();
  auto log_lambda = torch::tensor(std::log(o.lambda_init)).requires_grad_();
  torch::optim::Adam opt({a, b, log_lambda}, torch::optim::AdamOptions(o.lr));
  auto codes = [&]() {
    auto u = torch::tanh(a), v = torch::tanh(b);
    if (o.binary) u = straight_through_sign(u), v = straight_through_sign(v);
    return std::pair<torch::Tensor, torch::Tensor>{u, v};
  };

  std::filesystem::create_directories(o.out);
  auto gen = at::detail::createCPUGenerator(o.seed + 1);
  TrainerState state;
  state.params = {{"a", a}, {"b", b}, {"log_lambda", log_lambda}};
  state.optimizer = &opt, state.optimizer_kind = "adam";
  state.format = "flatnet-codes-checkpoint", state.size_hint = "another codes.length or codes.init?";
  const auto checkpoint = trainer_checkpoint_path(o.out);
  SeparableTrainSummary summary;
  int64_t first_step = 0;
  double seconds_before = 0;
  if (o.resume) {
    const auto restored = read_trainer_checkpoint(checkpoint, state);
    first_step = restored.step, seconds_before = restored.seconds;
    // The data order's and the noise's generator, checked before LibTorch reads it.
    const auto* rng = restored.file.find("rng");
    require(rng != nullptr, checkpoint, "lacks 'rng', the state of the data and noise generator");
    require_cpu_generator_state(*rng, checkpoint, "rng");
    gen.set_state(*rng);
    const auto start = restored.file.meta("val_psnr_start", checkpoint);
    require(is_decimal_number(start), checkpoint, "val_psnr_start '" + start.substr(0, 40) + "' is not a number");
    summary.val_psnr_start = std::strtod(start.c_str(), nullptr);
    state.run_id = restored.run_id;
  } else {
    const auto [u, v] = codes();
    summary.val_psnr_start = separable_psnr(u.detach(), v.detach(), std::exp(log_lambda.item<double>()), val, 99);
    std::cerr << "separable codes: validation PSNR at the start " << summary.val_psnr_start << " dB\n";
  }
  state.run_id = settle_run_id(o.out, o.resume, state.run_id, checkpoint, o.force);
  const char* header = "step,loss,throughput,lambda,val_psnr";
  CsvLog log = o.resume ? CsvLog::resume(o.out / "log.csv", header, first_step) : CsvLog(o.out / "log.csv", header);
  Series train_curve{"train (batch)", {}, {}}, val_curve{"validation", {}, {}};
  for (const auto& [x, loss] : log.column(1))  // a resumed run's rows up to its checkpoint (none for a new run)
    train_curve.x.push_back(x), train_curve.y.push_back(-10 * std::log10(std::max(1e-12, loss)));
  for (const auto& [x, psnr] : log.column(4)) val_curve.x.push_back(x), val_curve.y.push_back(psnr);
  double last_loss = 0, last_throughput = 0, last_val = std::nan("");
  auto lo = loop_schedule(o, "codes", "the last checkpoint (" + checkpoint.string() + ")");
  lo.first_step = first_step;
  lo.seconds_before = seconds_before;
  std::unique_ptr<TrainingLoop> loop;
  LoopHooks hooks;
  hooks.step = [&](int64_t step) {
    const auto idx = torch::randint(train_linear.size(0), {o.batch}, gen, torch::kLong);
    const auto X = train_linear.index_select(0, idx);
    const auto [u, v] = codes();
    const auto rec = capture_and_reconstruct(u, v, torch::exp(log_lambda), X, gen);
    const auto t = code_throughput(u, v);
    const auto loss = (rec - X).pow(2).mean() + throughput_penalty(t, o.target_throughput, o.throughput_tolerance);
    last_loss = loss.item<double>(), last_throughput = t.item<double>();
    opt.zero_grad();
    loss.backward();
    // An SVD with nearly equal singular values can give a non-finite gradient: that step is
    // skipped, and kNonFiniteLimit in a row stop (train/nonfinite.hpp).
    if (!std::isfinite(last_loss)) throw NonFiniteStep("loss", last_loss, step + 1);
    if (!all_finite({a.grad(), b.grad(), log_lambda.grad()}))
      throw NonFiniteStep("gradient of the codes or lambda", std::nan(""), step + 1);
    opt.step();
  };
  hooks.checkpoint = [&](int64_t done) {  // runs before the log row of the same step, and at the run's end
    const auto [uv, vv] = codes();
    last_val = summary.val_psnr = separable_psnr(uv.detach(), vv.detach(), std::exp(log_lambda.item<double>()), val, 99);
    val_curve.x.push_back(static_cast<double>(done));
    val_curve.y.push_back(last_val);
    std::ostringstream start;
    start << std::setprecision(17) << summary.val_psnr_start;
    write_trainer_checkpoint(checkpoint, state, done, loop->trained_seconds(), {{"val_psnr_start", start.str()}},
                             {{"rng", gen.get_state()}});
  };
  hooks.log = [&](int64_t done) {
    train_curve.x.push_back(static_cast<double>(done));
    train_curve.y.push_back(-10 * std::log10(std::max(1e-12, last_loss)));
    log.add(done, last_loss, last_throughput, std::exp(log_lambda.item<double>()), last_val);
    if (!std::isnan(last_val)) log.flush();  // the log on disk at each validation (CsvLog), and at the end
    last_val = std::nan("");
    return "loss " + std::to_string(last_loss) + " t " + std::to_string(last_throughput);
  };
  loop = std::make_unique<TrainingLoop>(lo, hooks);
  const auto r = loop->run();
  summary.steps = r.last_step;
  const auto [u, v] = codes();
  summary.lambda = std::exp(log_lambda.item<double>());
  summary.throughput = code_throughput(u, v).item<double>();
  summary.seconds = loop->trained_seconds();
  if (r.last_step == first_step && o.resume)  // a resumed run with no step left: its state's score
    summary.val_psnr = separable_psnr(u.detach(), v.detach(), summary.lambda, val, 99);
  save_code_pair(o.out / "codes.mat", u, v);
  write_text_atomically(o.out / "lambda.txt", std::to_string(summary.lambda) + "\n");
  log.flush();
  PlotOptions po;
  po.title = "separable codes: PSNR (Tikhonov, linear light)";
  po.xlabel = "step";
  po.ylabel = "PSNR dB";
  write_line_plot(o.out / "curve.png", {train_curve, val_curve}, po);
  return summary;
}

}  // namespace flatnet
