#include "train/gan_trainer.hpp"

#include <cmath>
#include <iomanip>

#include "core/error.hpp"
#include "core/precision.hpp"
#include "core/util.hpp"
#include "eval/metrics.hpp"
#include "recon/data_consistency.hpp"
#include "nn/fused_adam.hpp"
#include "train/distributed.hpp"
#include "train/loop.hpp"
#include "train/nonfinite.hpp"
#include "train/options.hpp"

namespace flatnet {

namespace {

const char* const kGanLogHeader =
    "step,loss,mse,ssim_loss,perceptual,adversarial,discriminator,lr,steps_per_s,feature_matching,frequency,chroma,"
    "gradient,stripe,psnr,detail,random_features";
// psnr and ssim: the mean over the conditions validated (data.val_light); the last three columns,
// each condition's own PSNR (dim and lamp empty unless the validation is judged).
const char* const kValHeader = "step,psnr,ssim,seconds,psnr_display,psnr_dim,psnr_lamp";

std::vector<torch::Tensor> clone_all(const std::vector<torch::Tensor>& tensors) {
  std::vector<torch::Tensor> out;
  for (const auto& t : tensors) out.push_back(t.detach().clone());
  return out;
}

torch::Tensor uniform(int64_t n, double lo, double hi, at::Generator& gen) {
  return at::rand({n, 1}, gen) * (hi - lo) + lo;
}

// The generator's output on what training shows it: the batch's whole scenes, or the step's crops.
// With the data-consistency layer, the whole scenes corrected by their captures.
torch::Tensor training_view(Generator& g, const Batch& batch, const TrainOptions& opt,
                            const std::vector<std::pair<int64_t, int64_t>>& corners,
                            const DataConsistency* consistency) {
  if (consistency) {
    require(corners.empty(), train_key(&TrainOptions::crop),
            "must be 0 with model.consistency: the correction needs whole scenes");
    return consistency->correct(batch.meas, g->forward(batch.meas));  // {B,3,N,N}
  }
  return corners.empty() ? g->forward(batch.meas) : g->forward_crops(batch.meas, corners, opt.crop);
}

// The loader of the training's batches from `first_step`, drawn from `seed`.
LoaderOptions training_loader(const TrainOptions& opt, uint64_t seed, int64_t first_step) {
  LoaderOptions lo;
  lo.batch = opt.batch;
  lo.seed = seed;
  lo.first_step = first_step;
  lo.workers = opt.workers;
  lo.noise_augment = opt.noise_augment;
  return lo;
}

}  // namespace

StepLosses& StepLosses::operator+=(const StepLosses& o) {
  loss += o.loss, mse += o.mse, ssim += o.ssim, perceptual += o.perceptual, adversarial += o.adversarial;
  discriminator += o.discriminator, feature_matching += o.feature_matching, frequency += o.frequency;
  chroma += o.chroma, gradient += o.gradient, stripe += o.stripe, psnr += o.psnr;
  detail += o.detail, random_features += o.random_features;
  return *this;
}

StepLosses StepLosses::operator/(double n) const {
  StepLosses m = *this;
  for (double* v : {&m.loss, &m.mse, &m.ssim, &m.perceptual, &m.adversarial, &m.discriminator, &m.feature_matching,
                    &m.frequency, &m.chroma, &m.gradient, &m.stripe, &m.psnr, &m.detail, &m.random_features})
    *v /= n;
  return m;
}

LrSchedule parse_lr_schedule(const std::string& s, const std::string& key) {
  if (s == "halving") return LrSchedule::halving;
  if (s == "cosine") return LrSchedule::cosine;
  throw Error("config: " + key + " must be halving or cosine, got '" + s + "'");
}

namespace {

// The share of the run done, in [0, 1]: of the time budget when there is one (it alone ends the
// run), else of the steps. The cosine schedule and co-design's freeze point both count it.
double run_share(const TrainOptions& opt, int64_t step, double seconds) {
  const double t = opt.minutes > 0 ? seconds / (60.0 * opt.minutes)
                                   : static_cast<double>(step) / std::max<int64_t>(1, opt.iterations);
  return std::min(1.0, t);
}

}  // namespace

double lr_factor(const TrainOptions& opt, int64_t step, double seconds) {
  if (opt.schedule == LrSchedule::cosine) return 0.5 * (1.0 + std::cos(M_PI * run_share(opt, step, seconds)));
  return std::pow(0.5, static_cast<double>(step / std::max<int64_t>(1, opt.lr_halve_every)));
}

std::vector<std::pair<int64_t, int64_t>> crop_corners(const TrainOptions& opt, int64_t batch, int64_t scene,
                                                      int64_t step) {
  if (opt.crop <= 0 || opt.crop >= scene) return {};
  auto gen = at::detail::createCPUGenerator(opt.seed * 15485863ULL + static_cast<uint64_t>(step));
  const auto rc = at::randint(0, scene - opt.crop + 1, {batch, 2}, gen, torch::kLong);
  std::vector<std::pair<int64_t, int64_t>> corners;
  for (int64_t b = 0; b < batch; ++b) corners.emplace_back(rc[b][0].item<int64_t>(), rc[b][1].item<int64_t>());
  return corners;
}

WeightAverage::WeightAverage(Generator& source, double decay)
    : source_(source), average_(Generator(source->options())), decay_(decay) {
  average_->prepare_training({false, false, false, false});
  torch::NoGradGuard no_grad;
  const auto dst = parameters_and_buffers(*average_), src = parameters_and_buffers(*source_);
  for (size_t i = 0; i < dst.size(); ++i) dst[i].copy_(src[i]);
  for (auto& p : average_->parameters()) p.set_requires_grad(false);
  average_->eval();
}

void WeightAverage::update(int64_t step) {
  torch::NoGradGuard no_grad;
  const double d = std::min(decay_, (1.0 + step) / (10.0 + step));
  const auto avg = average_->parameters(), live = source_->parameters();
  for (size_t i = 0; i < avg.size(); ++i) avg[i].mul_(d).add_(live[i].detach(), 1.0 - d);
  const auto avg_b = average_->buffers(), live_b = source_->buffers();
  for (size_t i = 0; i < avg_b.size(); ++i) avg_b[i].copy_(live_b[i]);
}

void refresh_batch_norm(Generator& g, BatchLoader& loader, int64_t batches, const TrainOptions& opt) {
  require(batches > 0, train_key(&TrainOptions::bn_refresh), "needs 1 or more batches");
  std::vector<std::pair<torch::nn::BatchNorm2dImpl*, c10::optional<double>>> layers;  // with their momentum
  for (const auto& m : g->modules(/*include_self=*/false))
    if (auto* bn = dynamic_cast<torch::nn::BatchNorm2dImpl*>(m.get())) {
      layers.emplace_back(bn, bn->options.momentum());
      bn->reset_running_stats();
      bn->options.momentum(c10::nullopt);  // running = mean over the batches seen (1 / num_batches_tracked)
    }
  const bool was_training = g->is_training();
  g->train();
  g->set_autocast_bf16(opt.bf16);
  {
    torch::NoGradGuard no_grad;
    for (int64_t i = 0; i < batches; ++i) {
      const auto batch = loader.next();
      (void)training_view(g, batch, opt, crop_corners(opt, batch.meas.size(0), batch.gt.size(-1), batch.step),
                          nullptr);  // batch norm sits before the correction
    }
  }
  for (auto& [bn, momentum] : layers) bn->options.momentum(momentum);
  g->train(was_training);
}

namespace {

torch::Tensor logits_fp32(Discriminator& d, const torch::Tensor& x, bool bf16) {
  AutocastGuard autocast(bf16);
  return d->forward(x).to(torch::kFloat32);
}

}  // namespace

StepLosses gan_step(Generator& g, Discriminator& d, Vgg16Features& vgg, torch::optim::Optimizer& opt_g,
                    torch::optim::Optimizer& opt_d, const TrainOptions& opt, const Batch& batch, int64_t step,
                    GradientAverager* sync, const DataConsistency* consistency) {
  StepLosses out;
  const bool adversarial = opt.trains_discriminator();
  const bool perceptual = opt.w_perceptual > 0;
  const bool warmup = step < opt.discriminator_warmup;
  auto label_gen = at::detail::createCPUGenerator(opt.seed * 104729ULL + static_cast<uint64_t>(step));
  const auto corners = crop_corners(opt, batch.meas.size(0), batch.gt.size(-1), step);
  const auto gt = crop_windows(batch.gt, corners, opt.crop);  // {B,3,n,n}
  g->set_autocast_bf16(opt.bf16);
  auto generate = [&] { return training_view(g, batch, opt, corners, consistency); };
  torch::Tensor fake;
  if (warmup) {
    torch::NoGradGuard no_grad;
    fake = generate();
  } else {
    fake = generate();  // {B,3,n,n}
  }
  if (adversarial) {  // discriminator step on real and detached fake images
    const int64_t B = fake.size(0);
    for (auto& p : d->parameters()) p.set_requires_grad(true);
    opt_d.zero_grad();
    const auto d_loss = torch::binary_cross_entropy_with_logits(logits_fp32(d, gt, opt.bf16),
                                                                uniform(B, opt.real_label_min, 1.0, label_gen)) +
                        torch::binary_cross_entropy_with_logits(logits_fp32(d, fake.detach(), opt.bf16),
                                                                uniform(B, 0.0, opt.fake_label_max, label_gen));
    out.discriminator = d_loss.item<double>();
    // Guard before any optimiser step: a non-finite loss must not reach the weights (run() skips the step).
    if (!std::isfinite(out.discriminator)) throw NonFiniteStep("discriminator loss", out.discriminator, step);
    d_loss.backward();
    if (sync) sync->average(d->parameters());
    opt_d.step();
  }
  if (!warmup) {  // generator step
    opt_g.zero_grad();
    const auto mse = torch::mse_loss(fake, gt);
    auto loss = opt.w_mse * mse;
    torch::Tensor perc, adv, structural;
    if (opt.w_ssim > 0) loss = loss + opt.w_ssim * (structural = ssim_loss(fake, gt));
    if (perceptual) loss = loss + opt.w_perceptual * (perc = perceptual_loss(vgg, fake, gt, opt.bf16));
    if (adversarial)
      for (auto& p : d->parameters()) p.set_requires_grad(false);
    if (opt.w_adversarial > 0) {
      adv = torch::binary_cross_entropy_with_logits(logits_fp32(d, fake, opt.bf16), torch::ones({fake.size(0), 1}));
      loss = loss + opt.w_adversarial * adv;
    }
    // The weight-free perceptual terms (issue 26), each logged on its own.
    auto add_term = [&](double weight, double& logged, const std::function<torch::Tensor()>& term) {
      if (weight <= 0) return;
      const auto t = term();
      logged = t.item<double>();
      loss = loss + weight * t;
    };
    add_term(opt.w_feature_matching, out.feature_matching,
             [&] { return feature_matching_loss(d, fake, gt, opt.bf16); });
    add_term(opt.w_frequency, out.frequency, [&] { return focal_frequency_loss(fake, gt); });
    add_term(opt.w_chroma, out.chroma, [&] { return chroma_loss(fake, gt); });
    add_term(opt.w_gradient, out.gradient, [&] { return gradient_loss(fake, gt); });
    add_term(opt.w_stripe, out.stripe, [&] { return stripe_loss(fake, gt); });
    add_term(opt.w_psnr, out.psnr, [&] { return psnr_loss(fake, gt); });
    add_term(opt.w_detail, out.detail, [&] { return detail_energy_loss(fake, gt); });
    add_term(opt.w_random_features, out.random_features, [&] { return random_feature_loss(fake, gt); });
    const double value = loss.item<double>();
    if (!std::isfinite(value))
      throw NonFiniteStep("generator loss (mse " + std::to_string(mse.item<double>()) + ")", value, step);
    loss.backward();
    if (sync) sync->average(g->parameters());
    opt_g.step();
    out.loss = value;
    out.mse = mse.item<double>();
    if (structural.defined()) out.ssim = structural.item<double>();
    if (perc.defined()) out.perceptual = perc.item<double>();
    if (adv.defined()) out.adversarial = adv.item<double>();
  }
  return out;
}

ValidationResult validate(Generator& generator, const std::vector<Sample>& samples, int64_t batch,
                          const std::filesystem::path& sheet, int sheet_rows, const DataConsistency* consistency) {
  ValidationResult r;
  if (samples.empty()) return r;
  std::vector<double> psnr_sum(kJudgedConditionCount, 0), ssim_sum(kJudgedConditionCount, 0);
  std::vector<int64_t> count(kJudgedConditionCount, 0);
  const bool was_training = generator->is_training();
  generator->eval();
  torch::NoGradGuard no_grad;
  std::vector<std::vector<torch::Tensor>> rows;
  std::vector<std::string> names;
  for (size_t i = 0; i < samples.size(); i += batch) {
    std::vector<torch::Tensor> meas;
    for (size_t j = i; j < std::min(samples.size(), i + batch); ++j) meas.push_back(samples[j].meas);
    const auto planes = torch::stack(meas);
    const auto out =
        consistency ? consistency->correct(planes, generator->forward(planes)) : generator->forward(planes);
    for (int64_t j = 0; j < out.size(0); ++j) {
      const auto& s = samples[i + j];
      const auto c = static_cast<size_t>(s.condition);
      psnr_sum.at(c) += psnr(out[j], s.gt);
      ssim_sum.at(c) += ssim(out[j], s.gt);
      ++count[c];
      if (static_cast<int>(rows.size()) < sheet_rows) rows.push_back({s.gt, out[j]}), names.push_back(s.name);
    }
  }
  int64_t conditions = 0;
  for (size_t c = 0; c < count.size(); ++c) {
    r.condition_psnr.push_back(count[c] > 0 ? psnr_sum[c] / count[c] : std::nan(""));
    if (count[c] == 0) continue;
    r.psnr += psnr_sum[c] / count[c];
    r.ssim += ssim_sum[c] / count[c];
    ++conditions;
  }
  r.psnr /= conditions;
  r.ssim /= conditions;
  if (!sheet.empty()) write_contact_sheet(sheet, {"truth", "flatnet"}, names, rows);
  if (was_training) generator->train();
  return r;
}

GanTrainer::GanTrainer(Generator generator, Discriminator discriminator, Vgg16Features vgg,
                       std::shared_ptr<const PairSource> train, std::vector<Sample> val, TrainOptions options,
                       ModelIdentity identity)
    : g_(std::move(generator)),
      d_(std::move(discriminator)),
      vgg_(std::move(vgg)),
      train_(std::move(train)),
      val_(std::move(val)),
      opt_(std::move(options)),
      identity_(std::move(identity)) {
  require(opt_.iterations > 0 && opt_.batch > 0, "train", "iterations and batch must be positive");
  require(opt_.w_perceptual <= 0 || !vgg_.is_empty(), train_key(&TrainOptions::w_perceptual),
          "a perceptual weight needs VGG-16 weights");
  g_->prepare_training({false, opt_.channels_last, false, opt_.gemm_upsample});
  if (opt_.channels_last && !vgg_.is_empty()) weights_to_channels_last(*vgg_);
  if (opt_.channels_last) weights_to_channels_last(*d_);
  // Two parameter groups: the inversion may learn at its own rate.
  std::vector<torch::Tensor> inversion, rest;
  for (const auto& p : g_->named_parameters())
    (p.key().rfind("inversion.", 0) == 0 ? inversion : rest).push_back(p.value());
  std::vector<torch::optim::OptimizerParamGroup> groups;
  groups.emplace_back(rest, std::make_unique<torch::optim::AdamOptions>(opt_.lr));
  if (!inversion.empty())
    groups.emplace_back(inversion, std::make_unique<torch::optim::AdamOptions>(opt_.lr * opt_.lr_inversion_scale));
  opt_g_ = std::make_unique<FusedAdam>(groups, torch::optim::AdamOptions(opt_.lr));
  opt_d_ = std::make_unique<FusedAdam>(d_->parameters(), torch::optim::AdamOptions(opt_.lr_discriminator));
  g_->set_autocast_bf16(opt_.bf16);
  // The one check of the decay for library callers (a config's value is range-checked when it loads).
  require(opt_.ema_decay >= 0 && opt_.ema_decay < 1, train_key(&TrainOptions::ema_decay), "must lie in [0, 1)");
  if (opt_.ema_decay > 0) {
    ema_ = std::make_unique<WeightAverage>(g_, opt_.ema_decay);
    ema_->average()->set_autocast_bf16(opt_.bf16);
  }
  state_.rng_state = at::detail::getDefaultCPUGenerator().get_state();
}

Generator& GanTrainer::exported() { return ema_ ? ema_->average() : g_; }

std::string GanTrainer::resume(const std::filesystem::path& checkpoint, std::optional<double> best_psnr) {
  state_ =
      load_checkpoint(checkpoint, g_, d_, *opt_g_, *opt_d_, ema_ ? &ema_->average() : nullptr, checkpoint_camera());
  // The best PSNR is the one best.ckpt holds: a kill between writing best.ckpt and latest.ckpt
  // leaves latest's record behind or ahead of the file, and no file would hold that score.
  const auto best = opt_.out / "best.ckpt";
  state_.best_psnr = !std::filesystem::exists(best) ? -1e9 : best_psnr ? *best_psnr : checkpoint_best_psnr(best);
  auto gen = at::detail::getDefaultCPUGenerator();
  gen.set_state(state_.rng_state);
  // A kill after latest.ckpt and before model.flatnet leaves the model a step behind: rewrite it.
  if (!sync_ || sync_->rank() == 0) save_model_file(opt_.out / "model.flatnet", exported(), exported_identity());
  std::ostringstream os;
  os << "resumed at step " << state_.step << ": generator" << (ema_ ? ", its moving average" : "")
     << ", discriminator, "
     << (state_.optimizers_restored ? "both optimisers" : "fresh optimisers (format-1 checkpoint)")
     << " and the random state restored; best validation PSNR ";
  if (std::filesystem::exists(best))
    os << std::fixed << std::setprecision(2) << state_.best_psnr << " dB (best.ckpt)";
  else
    os << "none yet (no best.ckpt)";
  return os.str();
}

void GanTrainer::set_distributed(GradientAverager* collectives) {
  sync_ = collectives;
  if (!sync_ || sync_->world_size() == 1) return;
  require(!camera_, "codes.learn", "co-design runs in one process");
  // Same starting point everywhere, whatever each rank initialised.
  sync_->broadcast(parameters_and_buffers(*g_));
  sync_->broadcast(parameters_and_buffers(*d_));
  opt_.progress = opt_.progress && sync_->rank() == 0;
}

void GanTrainer::set_learned_camera(CodePairCamera camera, CameraConfig geometry) {
  // Its batches are scenes, captured through codes that change: no fixed capture to refresh on.
  require(opt_.bn_refresh == 0, train_key(&TrainOptions::bn_refresh), "is not available with codes.learn");
  camera_ = std::move(camera);
  camera_geometry_ = std::move(geometry);
  opt_camera_ =
      std::make_unique<torch::optim::Adam>(camera_->parameters(), torch::optim::AdamOptions(camera_->options().lr));
}

CheckpointCamera GanTrainer::checkpoint_camera() {
  return camera_ ? CheckpointCamera{camera_.get(), opt_camera_.get()} : CheckpointCamera{};
}

bool GanTrainer::codes_frozen(int64_t step) const {
  return run_share(opt_, step, trained_seconds()) >= camera_->options().freeze_at;
}

torch::Tensor GanTrainer::capture_batch(const Batch& batch, int64_t step) {
  require(batch.scene.defined(), "codes.learn", "the training source gives captures, not scenes");
  // Noise from (seed, step): a resumed run captures as the straight one.
  auto gen = at::detail::createCPUGenerator(opt_.seed * 2654435761ULL + 17 + static_cast<uint64_t>(step));
  opt_camera_->zero_grad();
  const bool learning = !codes_frozen(step);
  torch::AutoGradMode grad_mode(learning);
  if (!learning && !frozen_rig_) frozen_rig_ = camera_->rig();  // the codes no longer change
  auto planes = camera_->capture(batch.scene, gen, true, learning ? nullptr : &*frozen_rig_);  // {B,4,h,w}
  if (opt_.noise_augment > 0) planes = planes + opt_.noise_augment * at::randn(planes.sizes(), gen);
  return learning ? planes : planes.detach();
}

void GanTrainer::step_codes(int64_t step) {
  if (codes_frozen(step)) return;
  const auto penalty = camera_->throughput_penalty();
  if (penalty.requires_grad()) penalty.backward();
  std::vector<torch::Tensor> grads;
  for (const auto& p : camera_->parameters()) {
    if (!p.grad().defined()) return;  // the generator did not step (discriminator warm-up)
    grads.push_back(p.grad());
  }
  if (!all_finite(grads)) throw NonFiniteStep("gradient of the codes", std::nan(""), step);
  opt_camera_->step();
}

void GanTrainer::set_learning_rates(int64_t step) {
  const double f = lr_factor(opt_, step, trained_seconds());
  auto& groups = opt_g_->param_groups();
  static_cast<torch::optim::AdamOptions&>(groups[0].options()).lr(opt_.lr * f);
  if (groups.size() > 1)
    static_cast<torch::optim::AdamOptions&>(groups[1].options()).lr(opt_.lr * opt_.lr_inversion_scale * f);
  static_cast<torch::optim::AdamOptions&>(opt_d_->param_groups()[0].options()).lr(opt_.lr_discriminator * f);
  if (opt_camera_)
    static_cast<torch::optim::AdamOptions&>(opt_camera_->param_groups()[0].options()).lr(camera_->options().lr * f);
}

void GanTrainer::checkpoint_and_validate(TrainSummary& summary) {
  const auto t0 = std::chrono::steady_clock::now();
  if (camera_) {  // the validation scenes through the current codes, with the same noise every time
    torch::NoGradGuard no_grad;
    auto gen = at::detail::createCPUGenerator(opt_.seed + 99);
    const auto rig = frozen_rig_ ? *frozen_rig_ : camera_->rig();
    for (auto& s : val_) s.meas = camera_->capture(s.scene.unsqueeze(0), gen, true, &rig)[0];
  }
  if (opt_.bn_refresh > 0) refresh_exported_statistics();
  const auto v = validate(exported(), val_, opt_.batch, opt_.out / "samples.png", 4, consistency_.get());
  const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  summary.last_psnr = v.psnr;
  summary.last_ssim = v.ssim;
  auto condition = [&](size_t c) {  // empty where no sample was validated under that light
    std::ostringstream os;
    if (c < v.condition_psnr.size() && !std::isnan(v.condition_psnr[c])) os << v.condition_psnr[c];
    return os.str();
  };
  val_log_->add(state_.step, v.psnr, v.ssim, secs, condition(0), condition(1), condition(2));  // 6 significant digits
  val_log_->flush();
  const bool best = v.psnr > state_.best_psnr;
  if (best) state_.best_psnr = v.psnr;
  state_.rng_state = at::detail::getDefaultCPUGenerator().get_state();
  state_.train_seconds = trained_seconds();
  Generator* ema = ema_ ? &ema_->average() : nullptr;
  // The order makes the set consistent after a kill at any instant: best.ckpt first (resume takes
  // the best PSNR from it), then latest.ckpt (resume continues from it), then model.flatnet, which
  // follows the latest weights (not picked on validation data) and is rewritten on resume. Each
  // file is written atomically.
  // A co-design run's camera first: the model and checkpoints written next belong to these codes.
  if (camera_) write_code_camera(opt_.out / "camera", camera_, camera_geometry_);
  if (best) {
    summary.best_psnr = v.psnr;
    summary.best_ssim = v.ssim;
    save_checkpoint(opt_.out / "best.ckpt", g_, d_, *opt_g_, *opt_d_, state_, identity_, ema, checkpoint_camera());
  }
  save_resumable();
  save_model_file(opt_.out / "model.flatnet", exported(), exported_identity());
  if (opt_.keep_every > 0 && state_.step % opt_.keep_every == 0) keep_model();
}

void GanTrainer::save_resumable() {
  state_.rng_state = at::detail::getDefaultCPUGenerator().get_state();
  state_.train_seconds = trained_seconds();
  save_checkpoint(opt_.out / "latest.ckpt", g_, d_, *opt_g_, *opt_d_, state_, identity_,
                  ema_ ? &ema_->average() : nullptr, checkpoint_camera());
}

// A copy of the exported model that later validations do not replace: RUN/kept/step<N>.flatnet
// (the mean of a run's last ones, `flatnet export --average-of`, often beats its last alone).
void GanTrainer::keep_model() {
  const auto kept = opt_.out / "kept";
  // Never written through a link flatnet did not make: the models would land in another folder.
  require(!std::filesystem::is_symlink(kept), kept,
          "is a link; kept models are written only into the run's own folder (remove the link, or start afresh "
          "with --force)");
  std::filesystem::create_directories(kept);
  save_model_file(kept / ("step" + std::to_string(state_.step) + ".flatnet"), exported(), exported_identity());
}

ModelIdentity GanTrainer::exported_identity() const {
  auto identity = identity_;
  identity.provenance.trained_steps = std::to_string(state_.step);
  identity.provenance.train_seconds = std::to_string(std::lround(trained_seconds()));
  if (state_.best_psnr > -1e8) identity.provenance.best_val_psnr = std::to_string(state_.best_psnr);
  identity.provenance.source =
      std::string("flatnet train (") + (ema_ ? "moving average of the weights" : "last weights") + ")";
  return identity;
}

void GanTrainer::refresh_exported_statistics() {
  // Batches of their own (another seed), from the step reached: the training's data order, noise
  // and random state are untouched, so a resumed run still repeats the straight one.
  BatchLoader loader(train_, training_loader(opt_, opt_.seed + kRefreshSeedOffset, state_.step));
  refresh_batch_norm(exported(), loader, opt_.bn_refresh, opt_);
}

// One generator (and discriminator) step on the loader's next batch; a non-finite one puts the
// batch-norm statistics back and rethrows (the loop skips it).
void GanTrainer::train_step(BatchLoader& loader, int64_t step, StepTally& tally) {
  set_learning_rates(step);
  auto batch = loader.next();
  const auto statistics_before = clone_all(tally.statistics);
  StepLosses l;
  try {
    if (camera_) batch.meas = capture_batch(batch, step);
    l = gan_step(g_, d_, vgg_, *opt_g_, *opt_d_, opt_, batch, step, sync_, consistency_.get());
    if (camera_) step_codes(step);
  } catch (const NonFiniteStep&) {
    torch::NoGradGuard no_grad;
    for (size_t i = 0; i < tally.statistics.size(); ++i) tally.statistics[i].copy_(statistics_before[i]);
    throw;
  }
  if (ema_) ema_->update(step);
  tally.sums += l;
  ++tally.steps;
  if (sync_ && sync_->world_size() > 1) {
    // Batch-norm running statistics follow rank 0's (as DistributedDataParallel's broadcast_buffers).
    sync_->broadcast(tally.statistics);
    if (opt_.check_sync_every > 0 && (step + 1) % opt_.check_sync_every == 0) {
      sync_->check_identical(g_->parameters(), "generator parameters after step " + std::to_string(step + 1));
      sync_->check_identical(d_->parameters(), "discriminator parameters after step " + std::to_string(step + 1));
    }
  }
}

// log.csv's row for the steps since the last one; returns the progress bar's status.
std::string GanTrainer::log_row(int64_t done, int64_t first_step, StepTally& tally) {
  const double elapsed = std::max(1e-9, loop_->elapsed_seconds());
  const auto m = tally.sums / static_cast<double>(std::max<int64_t>(1, tally.steps));
  const double lr = static_cast<torch::optim::AdamOptions&>(opt_g_->param_groups()[0].options()).lr();
  log_->add(done, m.loss, m.mse, m.ssim, m.perceptual, m.adversarial, m.discriminator, lr,
            (done - first_step) / elapsed, m.feature_matching, m.frequency, m.chroma, m.gradient, m.stripe, m.psnr,
            m.detail, m.random_features);
  log_->flush();
  std::ostringstream status;
  status << "step " << done << " loss " << std::setprecision(4) << m.loss << " mse " << m.mse;
  if (opt_.trains_discriminator()) status << " D " << m.discriminator;
  if (camera_) {
    torch::NoGradGuard no_grad;
    status << " throughput " << std::setprecision(3) << camera_->throughput().item<double>()
           << (codes_frozen(done) ? " (codes fixed)" : "");
  }
  tally.sums = StepLosses{};
  tally.steps = 0;
  return status.str();
}

TrainSummary GanTrainer::run() {
  TrainSummary summary;
  summary.first_step = state_.step;
  summary.best_psnr = state_.best_psnr;
  auto lo = training_loader(opt_, opt_.seed, state_.step);
  if (sync_) lo.world_size = sync_->world_size(), lo.rank = sync_->rank();
  BatchLoader loader(train_, lo);
  const bool writer = !sync_ || sync_->rank() == 0;  // only rank 0 writes logs and checkpoints
  if (writer) {
    std::filesystem::create_directories(opt_.out);
    // A resumed run's logs keep their rows up to the checkpoint (the later ones are repeated now).
    log_ = CsvLog::resume(opt_.out / "log.csv", kGanLogHeader, state_.step);
    val_log_ = CsvLog::resume(opt_.out / "val.csv", kValHeader, state_.step);
  }
  g_->train();
  d_->train();
  StepTally tally;  // since the last log row
  // Batch norm's running statistics change in the forward pass: a skipped step puts them back.
  tally.statistics = g_->buffers();
  for (const auto& b : d_->buffers()) tally.statistics.push_back(b);

  auto options = loop_schedule(
      opt_, "train", (opt_.out / "latest.ckpt").string() + " (the last validation's, if the run reached one)");
  options.first_step = state_.step;
  options.seconds_before = state_.train_seconds;
  options.writer = writer;
  options.save_minutes = opt_.save_minutes;
  // Data-parallel ranks must take the same steps: a skip on one rank alone would pair its next
  // collective with another rank's current one, so there the first non-finite step stops.
  options.skip_nonfinite = !(sync_ && sync_->world_size() > 1);
  LoopHooks hooks;
  hooks.step = [&](int64_t step) { train_step(loader, step, tally); };
  hooks.advanced = [&](int64_t done) { state_.step = done; };
  hooks.log = [&](int64_t done) { return log_row(done, summary.first_step, tally); };
  hooks.checkpoint = [&](int64_t) { checkpoint_and_validate(summary); };
  hooks.save = [&](int64_t) { save_resumable(); };
  if (sync_) hooks.any_rank = [&](bool local) { return sync_->any(local); };

  TrainingLoop loop(options, hooks);
  loop_ = &loop;
  LoopResult r;
  try {
    r = loop.run();
  } catch (...) {
    loop_ = nullptr;
    throw;
  }
  loop_ = nullptr;
  summary.budget_reached = r.budget_reached;
  summary.last_step = r.last_step;
  summary.seconds = r.seconds;
  summary.steps_per_s = summary.seconds > 0 ? (summary.last_step - summary.first_step) / summary.seconds : 0;
  summary.loader_wait_s = loader.wait_seconds();
  if (summary.best_psnr < -1e8) summary.best_psnr = state_.best_psnr;
  return summary;
}

}  // namespace flatnet
