#include "train/gan_trainer.hpp"

#include <fstream>
#include <iomanip>

#include "core/error.hpp"
#include "core/util.hpp"
#include "eval/metrics.hpp"
#include "train/distributed.hpp"

namespace flatnet {


namespace {

// Keeps the rows of a CSV log whose first field (the step) is <= last_step; used on resume so
// the log continues without duplicates.
void truncate_log(const std::filesystem::path& path, int64_t last_step) {
  if (!std::filesystem::exists(path)) return;
  std::ifstream in(path);
  std::string line, kept;
  bool header = true;
  while (std::getline(in, line)) {
    if (header || std::stoll(line.substr(0, line.find(','))) <= last_step) kept += line + "\n";
    header = false;
  }
  write_text_atomically(path, kept);
}

void append_line(const std::filesystem::path& path, const std::string& header, const std::string& line) {
  const bool fresh = !std::filesystem::exists(path);
  std::ofstream out(path, std::ios::app);
  if (fresh) out << header << "\n";
  out << line << "\n";
}

torch::Tensor uniform(int64_t n, double lo, double hi, at::Generator& gen) {
  return at::rand({n, 1}, gen) * (hi - lo) + lo;
}

}  // namespace

StepLosses gan_step(Generator& g, Discriminator& d, Vgg16Features& vgg, torch::optim::Optimizer& opt_g,
                    torch::optim::Optimizer& opt_d, const TrainOptions& opt, const Batch& batch, int64_t step,
                    GradientAverager* sync) {
  StepLosses out;
  const bool adversarial = opt.w_adversarial > 0;
  const bool perceptual = opt.w_perceptual > 0;
  const bool warmup = step < opt.discriminator_warmup;
  auto label_gen = at::detail::createCPUGenerator(opt.seed * 104729ULL + static_cast<uint64_t>(step));
  torch::Tensor fake;
  if (warmup) {
    torch::NoGradGuard no_grad;
    fake = g->forward(batch.meas);
  } else {
    fake = g->forward(batch.meas);  // {B,3,N,N}
  }
  if (adversarial) {  // discriminator step on real and detached fake images
    const int64_t B = fake.size(0);
    for (auto& p : d->parameters()) p.set_requires_grad(true);
    opt_d.zero_grad();
    const auto d_loss =
        torch::binary_cross_entropy_with_logits(d->forward(batch.gt), uniform(B, opt.real_label_min, 1.0, label_gen)) +
        torch::binary_cross_entropy_with_logits(d->forward(fake.detach()), uniform(B, 0.0, opt.fake_label_max, label_gen));
    d_loss.backward();
    if (sync) sync->average(d->parameters());
    opt_d.step();
    out.discriminator = d_loss.item<double>();
  }
  if (!warmup) {  // generator step
    opt_g.zero_grad();
    const auto mse = torch::mse_loss(fake, batch.gt);
    auto loss = opt.w_mse * mse;
    torch::Tensor perc, adv;
    if (perceptual) loss = loss + opt.w_perceptual * (perc = perceptual_loss(vgg, fake, batch.gt));
    if (adversarial) {
      for (auto& p : d->parameters()) p.set_requires_grad(false);
      adv = torch::binary_cross_entropy_with_logits(d->forward(fake), torch::ones({fake.size(0), 1}));
      loss = loss + opt.w_adversarial * adv;
    }
    const double value = loss.item<double>();
    if (!std::isfinite(value) || !std::isfinite(out.discriminator)) {
      std::ostringstream os;
      os << "training diverged: the loss is " << value << " at step " << step << " (mse " << mse.item<double>()
         << ", discriminator " << out.discriminator << "); nothing was saved from this step; the last good checkpoint is "
         << (opt.out / "latest.ckpt").string() << ". Try a lower train.lr.";
      throw Error(os.str());
    }
    loss.backward();
    if (sync) sync->average(g->parameters());
    opt_g.step();
    out.loss = value, out.mse = mse.item<double>();
    if (perc.defined()) out.perceptual = perc.item<double>();
    if (adv.defined()) out.adversarial = adv.item<double>();
  }
  return out;
}

ValidationResult validate(Generator& generator, const std::vector<Sample>& samples, int64_t batch,
                          const std::filesystem::path& sheet, int sheet_rows) {
  ValidationResult r;
  if (samples.empty()) return r;
  const bool was_training = generator->is_training();
  generator->eval();
  torch::NoGradGuard no_grad;
  std::vector<std::vector<torch::Tensor>> rows;
  std::vector<std::string> names;
  for (size_t i = 0; i < samples.size(); i += batch) {
    std::vector<torch::Tensor> meas;
    for (size_t j = i; j < std::min(samples.size(), i + batch); ++j) meas.push_back(samples[j].meas);
    const auto out = generator->forward(torch::stack(meas));
    for (int64_t j = 0; j < out.size(0); ++j) {
      const auto& s = samples[i + j];
      r.psnr += psnr(out[j], s.gt);
      r.ssim += ssim(out[j], s.gt);
      if (static_cast<int>(rows.size()) < sheet_rows) rows.push_back({s.gt, out[j]}), names.push_back(s.name);
    }
  }
  r.psnr /= samples.size();
  r.ssim /= samples.size();
  if (!sheet.empty()) write_contact_sheet(sheet, {"truth", "flatnet"}, names, rows);
  if (was_training) generator->train();
  return r;
}

GanTrainer::GanTrainer(Generator generator, Discriminator discriminator, Vgg16Features vgg,
                       std::shared_ptr<const PairSource> train, std::vector<Sample> val, TrainOptions options,
                       Config config, CameraConfig camera)
    : g_(std::move(generator)), d_(std::move(discriminator)), vgg_(std::move(vgg)), train_(std::move(train)),
      val_(std::move(val)), opt_(std::move(options)), config_(std::move(config)), camera_(std::move(camera)) {
  require(opt_.iterations > 0 && opt_.batch > 0, "train", "iterations and batch must be positive");
  require(opt_.w_perceptual <= 0 || !vgg_.is_empty(), "loss.perceptual", "a perceptual weight needs VGG-16 weights");
  g_->prepare_training({false, opt_.channels_last, false, opt_.gemm_upsample});
  // Two parameter groups: the inversion may learn at its own rate.
  std::vector<torch::Tensor> inversion, rest;
  for (const auto& p : g_->named_parameters()) (p.key().rfind("inversion.", 0) == 0 ? inversion : rest).push_back(p.value());
  std::vector<torch::optim::OptimizerParamGroup> groups;
  groups.emplace_back(rest, std::make_unique<torch::optim::AdamOptions>(opt_.lr));
  if (!inversion.empty())
    groups.emplace_back(inversion, std::make_unique<torch::optim::AdamOptions>(opt_.lr * opt_.lr_inversion_scale));
  opt_g_ = std::make_unique<torch::optim::Adam>(groups, torch::optim::AdamOptions(opt_.lr));
  opt_d_ = std::make_unique<torch::optim::Adam>(d_->parameters(), torch::optim::AdamOptions(opt_.lr_discriminator));
  state_.rng_state = at::detail::getDefaultCPUGenerator().get_state();
}

void GanTrainer::resume(const std::filesystem::path& checkpoint) {
  state_ = load_checkpoint(checkpoint, g_, d_, *opt_g_, *opt_d_);
  auto gen = at::detail::getDefaultCPUGenerator();
  gen.set_state(state_.rng_state);
  truncate_log(opt_.out / "log.csv", state_.step);
  truncate_log(opt_.out / "val.csv", state_.step);
}

void GanTrainer::set_distributed(GradientAverager* collectives) {
  sync_ = collectives;
  if (!sync_ || sync_->world_size() == 1) return;
  // Same starting point everywhere, whatever each rank initialised.
  sync_->broadcast(parameters_and_buffers(*g_));
  sync_->broadcast(parameters_and_buffers(*d_));
  opt_.progress = opt_.progress && sync_->rank() == 0;
}

void GanTrainer::set_learning_rates(int64_t step) {
  const double f = std::pow(0.5, static_cast<double>(step / std::max<int64_t>(1, opt_.lr_halve_every)));
  auto& groups = opt_g_->param_groups();
  static_cast<torch::optim::AdamOptions&>(groups[0].options()).lr(opt_.lr * f);
  if (groups.size() > 1) static_cast<torch::optim::AdamOptions&>(groups[1].options()).lr(opt_.lr * opt_.lr_inversion_scale * f);
  static_cast<torch::optim::AdamOptions&>(opt_d_->param_groups()[0].options()).lr(opt_.lr_discriminator * f);
}

void GanTrainer::checkpoint_and_validate(TrainSummary& summary) {
  const auto t0 = std::chrono::steady_clock::now();
  const auto v = validate(g_, val_, opt_.batch, opt_.out / "samples.png");
  const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  summary.last_psnr = v.psnr, summary.last_ssim = v.ssim;
  std::ostringstream line;
  line << state_.step << "," << std::setprecision(6) << v.psnr << "," << v.ssim << "," << secs;
  append_line(opt_.out / "val.csv", "step,psnr,ssim,seconds", line.str());
  const bool best = v.psnr > state_.best_psnr;
  if (best) state_.best_psnr = v.psnr;
  state_.rng_state = at::detail::getDefaultCPUGenerator().get_state();
  save_checkpoint(opt_.out / "latest.ckpt", g_, d_, *opt_g_, *opt_d_, state_, config_, camera_);
  if (best) {
    summary.best_psnr = v.psnr, summary.best_ssim = v.ssim;
    save_checkpoint(opt_.out / "best.ckpt", g_, d_, *opt_g_, *opt_d_, state_, config_, camera_);
    save_model_file(opt_.out / "model.flatnet", g_, config_, camera_);
  }
}

TrainSummary GanTrainer::run() {
  TrainSummary summary;
  summary.first_step = state_.step;
  summary.best_psnr = state_.best_psnr;
  LoaderOptions lo;
  lo.batch = opt_.batch;
  lo.seed = opt_.seed;
  lo.first_step = state_.step;
  lo.workers = opt_.workers;
  lo.noise_augment = opt_.noise_augment;
  if (sync_) lo.world_size = sync_->world_size(), lo.rank = sync_->rank();
  BatchLoader loader(train_, lo);
  const bool writer = !sync_ || sync_->rank() == 0;  // only rank 0 writes logs and checkpoints
  if (writer) std::filesystem::create_directories(opt_.out);
  const bool adversarial = opt_.w_adversarial > 0;
  g_->train();
  d_->train();
  Progress progress("train", opt_.iterations - state_.step, opt_.progress);
  const auto start = std::chrono::steady_clock::now();
  double sum_loss = 0, sum_mse = 0, sum_perc = 0, sum_adv = 0, sum_d = 0;
  int64_t n_logged = 0;
  auto stop = [&] { return sync_ ? sync_->any(interrupted()) : interrupted(); };
  bool stopping = false;
  int64_t checkpointed = -1;
  while (state_.step < opt_.iterations && !(stopping = stop())) {
    const int64_t step = state_.step;
    set_learning_rates(step);
    const auto batch = loader.next();
    const auto l = gan_step(g_, d_, vgg_, *opt_g_, *opt_d_, opt_, batch, step, sync_);
    sum_loss += l.loss, sum_mse += l.mse, sum_perc += l.perceptual, sum_adv += l.adversarial;
    const double d_value = l.discriminator;
    if (sync_ && sync_->world_size() > 1) {
      // Batch-norm running statistics follow rank 0's (as DistributedDataParallel's broadcast_buffers).
      std::vector<torch::Tensor> buffers = g_->buffers(), d_buffers = d_->buffers();
      buffers.insert(buffers.end(), d_buffers.begin(), d_buffers.end());
      sync_->broadcast(buffers);
      if (opt_.check_sync_every > 0 && (step + 1) % opt_.check_sync_every == 0) {
        sync_->check_identical(g_->parameters(), "generator parameters after step " + std::to_string(step + 1));
        sync_->check_identical(d_->parameters(), "discriminator parameters after step " + std::to_string(step + 1));
      }
    }
    sum_d += d_value;
    ++n_logged;
    state_.step = step + 1;
    progress.tick();
    if (writer && (state_.step % opt_.log_every == 0 || state_.step == opt_.iterations)) {
      const double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
      std::ostringstream line, status;
      line << state_.step << "," << std::setprecision(6) << sum_loss / n_logged << "," << sum_mse / n_logged << ","
           << sum_perc / n_logged << "," << sum_adv / n_logged << "," << sum_d / n_logged << ","
           << static_cast<torch::optim::AdamOptions&>(opt_g_->param_groups()[0].options()).lr() << ","
           << (state_.step - summary.first_step) / elapsed;
      append_line(opt_.out / "log.csv", "step,loss,mse,perceptual,adversarial,discriminator,lr,steps_per_s", line.str());
      status << "step " << state_.step << " loss " << std::setprecision(4) << sum_loss / n_logged << " mse "
             << sum_mse / n_logged;
      if (adversarial) status << " D " << sum_d / n_logged;
      progress.set_status(status.str());
      sum_loss = sum_mse = sum_perc = sum_adv = sum_d = 0;
      n_logged = 0;
    }
    if (writer && (state_.step % opt_.val_every == 0 || state_.step == opt_.iterations)) {
      checkpoint_and_validate(summary);
      checkpointed = state_.step;
    }
  }
  if (stopping && writer && checkpointed != state_.step) checkpoint_and_validate(summary);  // Ctrl-C loses nothing
  progress.finish();
  summary.last_step = state_.step;
  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  summary.steps_per_s = summary.seconds > 0 ? (summary.last_step - summary.first_step) / summary.seconds : 0;
  summary.loader_wait_s = loader.wait_seconds();
  if (summary.best_psnr < -1e8) summary.best_psnr = state_.best_psnr;
  return summary;
}

}  // namespace flatnet
