#pragma once
// FlatNet's adversarial training (Khan et al. 2019, sec. 4): per batch one discriminator step on
// real images and detached generator outputs, then one generator step on
//   l1 * MSE + l2 * (MSE(relu2_2) + MSE(relu4_3)) + l3 * BCE(D(G(y)), 1),
// Adam for both, learning rates halved every `lr_halve_every` steps. Validation (PSNR, SSIM, a
// sample sheet) and atomic checkpoints (latest.ckpt, best.ckpt, model.flatnet) every `val_every`
// steps; a resumed run continues with the same data order, noise and weights, bit for bit.
#include <atomic>
#include <chrono>
#include <filesystem>
#include <memory>
#include <optional>
#include <vector>

#include "io/camera_config.hpp"
#include "nn/generator.hpp"
#include "nn/losses.hpp"
#include "train/codesign.hpp"
#include "train/csv_log.hpp"
#include "train/data.hpp"
#include "train/loop.hpp"
#include "nn/checkpoint.hpp"
#include "nn/model_file.hpp"

namespace flatnet {

class DataConsistency;  // recon/data_consistency.hpp

enum class LrSchedule { halving, cosine };
LrSchedule parse_lr_schedule(const std::string& s, const std::string& key = "train.schedule");

// The schedule (train/loop.hpp): 20,000 steps of 4, lr 1e-4, validation every 500 and a log row every
// 10 steps; with train.minutes the run stops cleanly at the budget with a final checkpoint and model
// file, and a cosine schedule spans the budget.
struct TrainOptions : Schedule {
  TrainOptions() : Schedule{20000, 0, 4, 1e-4, 0, 500, 10, true} {}
  double lr_discriminator = 1e-4, lr_inversion_scale = 1.0;
  // halving: lr * 0.5^floor(step / lr_halve_every) (the thesis); cosine: lr * (1 + cos(pi t)) / 2 with
  // t = step / iterations, or with a time budget the larger of that and the budget's elapsed fraction.
  LrSchedule schedule = LrSchedule::halving;
  int64_t lr_halve_every = 5000;
  int64_t discriminator_warmup = 0;
  double noise_augment = 0.003;
  int workers = 1;
  int64_t val_count = 64;  // validation samples loaded by the caller (0: all)
  double w_mse = 1.0, w_perceptual = 1.2, w_adversarial = 0.6;
  double w_ssim = 0.0;  // weight of the structural term 1 - SSIM
  // Terms that need no downloaded weights (nn/losses.hpp): feature matching on the discriminator's
  // layers (trains the discriminator even when w_adversarial is 0), focal frequency, CIELAB chroma, gradient,
  // row and column stripes (nn/losses.hpp stripe_loss), minus the mean PSNR (psnr_loss).
  double w_feature_matching = 0.0, w_frequency = 0.0, w_chroma = 0.0, w_gradient = 0.0, w_stripe = 0.0, w_psnr = 0.0;
  // Issue 112: local detail energy (detail_energy_loss) and a fixed random network's features
  // (random_feature_loss).
  double w_detail = 0.0, w_random_features = 0.0;
  // The discriminator is trained (one step per generator step) when a term needs it.
  bool trains_discriminator() const { return w_adversarial > 0 || w_feature_matching > 0; }
  double ema_decay =
      0.0;  // exponential moving average of the generator's weights (0: off); used to validate and export
  // Every this many steps (at a validation), the exported model is also kept as
  // RUN/kept/step<N>.flatnet, for `flatnet export --average-of` over a run's end (0: off).
  int64_t keep_every = 0;
  // Batches over which the validated and exported weights' batch-norm statistics are re-estimated
  // before each validation (0: off; refresh_batch_norm below).
  int64_t bn_refresh = 0;
  // Wall-clock minutes between saves of latest.ckpt alone, between validations (0: off): a run killed
  // without warning loses at most this much however large val_every is (TrainingLoop's save hook).
  double save_minutes = 10;
  int64_t crop = 0;  // the enhancer trains on random crop x crop windows of the first stage (0: whole scenes)
  std::string precision = "auto";  // auto | fp32 | bf16, as configured; resolved into bf16 for this CPU
  bool bf16 = false;  // bf16 autocast for the enhancer and discriminator (fp32 master weights and Adam state)
  double real_label_min = 0.7, fake_label_max = 0.3;
  bool channels_last = true;     // exact speed-ups (InferenceLevers): NHWC activations,
  bool gemm_upsample = true;     // transposed convolutions as GEMMs
  int64_t check_sync_every = 0;  // distributed: verify bit-identical parameters every N steps (0: never)
  std::filesystem::path out;     // run folder: latest.ckpt, best.ckpt, model.flatnet, log.csv, val.csv, samples.png
};

struct TrainSummary {
  int64_t first_step = 0, last_step = 0;
  bool budget_reached = false;  // stopped by train.minutes
  double best_psnr = 0, best_ssim = 0, last_psnr = 0, last_ssim = 0;
  double seconds = 0, steps_per_s = 0, loader_wait_s = 0;
};

struct ValidationResult {
  double psnr = 0, ssim = 0;  // the mean over the conditions present of each one's mean
  // Per Sample::condition (kJudgedConditions): its mean PSNR, NaN where no sample had it.
  std::vector<double> condition_psnr;
};

// Runs the generator over samples (eval mode, batches of `batch`); returns means and, when
// `sheet` is set, writes a contact sheet of the first `sheet_rows` (truth | output). Samples
// under several lights (judged validation) weigh each condition alike, whatever its count.
// With `consistency`, each output is corrected by its capture first (model.consistency).
ValidationResult validate(Generator& generator, const std::vector<Sample>& samples, int64_t batch,
                          const std::filesystem::path& sheet = {}, int sheet_rows = 4,
                          const DataConsistency* consistency = nullptr);

struct StepLosses {
  double loss = 0, mse = 0, ssim = 0, perceptual = 0, adversarial = 0, discriminator = 0;
  double feature_matching = 0, frequency = 0, chroma = 0, gradient = 0, stripe = 0, psnr = 0;
  double detail = 0, random_features = 0;
  StepLosses& operator+=(const StepLosses& o);
  StepLosses operator/(double n) const;
};

// Learning-rate factor (relative to train.lr) at `step` under the options' schedule.
// `seconds`: training time so far (resumes included), for a cosine schedule over a time budget.
double lr_factor(const TrainOptions& opt, int64_t step, double seconds = 0);

// The crop corners of step `step`'s batch: one uniform (row, col) per sample, drawn from (seed,
// step) so a resumed run crops as the straight one. Empty when opt.crop is 0 or the scene size.
std::vector<std::pair<int64_t, int64_t>> crop_corners(const TrainOptions& opt, int64_t batch, int64_t scene,
                                                      int64_t step);

// Exponential moving average of a generator's weights (batch-norm statistics copied as they are).
// The decay warms up as min(decay, (1 + updates) / (10 + updates)) so early averages are not
// dominated by the random initialisation.
class WeightAverage {
 public:
  WeightAverage(Generator& source, double decay);
  void update(int64_t step);  // after the optimiser step `step`
  Generator& average() { return average_; }

 private:
  Generator& source_;
  Generator average_;
  double decay_;
};

// Sets every batch-norm layer's running mean and variance in `g` to the plain mean of its batch
// statistics over `batches` batches from `loader` (forward passes in training mode on the training
// crops, no gradients), as SWA's update_bn (Izmailov et al. 2018, sec. 3.2). A moving average of the
// weights otherwise carries the live network's statistics: measured with other weights, and over
// only the last ~1/momentum batches (at momentum 0.01 the two agree within 0.08 dB: results record).
void refresh_batch_norm(Generator& g, BatchLoader& loader, int64_t batches, const TrainOptions& opt);

// Data-parallel training's collectives (implemented with c10d in train/distributed.hpp).
class GradientAverager {
 public:
  virtual ~GradientAverager() = default;
  virtual int rank() const = 0;
  virtual int world_size() const = 0;
  // Gradients of `params` <- their mean over all processes, in place.
  virtual void average(const std::vector<torch::Tensor>& params) = 0;
  // Tensors <- rank 0's values.
  virtual void broadcast(const std::vector<torch::Tensor>& tensors) = 0;
  // Errors (on every rank) when the ranks' tensors are not bit-identical.
  virtual void check_identical(const std::vector<torch::Tensor>& tensors, const std::string& what) = 0;
  // True on every rank when it is true on any.
  virtual bool any(bool flag) = 0;
};

// One training step (see the file comment) on `batch`; `step` seeds the label smoothing. With
// `sync`, gradients are averaged across processes before each optimiser step. Throws
// NonFiniteStep (train/nonfinite.hpp) on a non-finite loss before any parameter changes; run()
// skips such a step, and stops after kNonFiniteLimit in a row. With `consistency`, the generator's
// pictures are corrected by their captures (a layer of the model, model.consistency) before the
// losses see them: whole scenes only (train.crop 0).
StepLosses gan_step(Generator& g, Discriminator& d, Vgg16Features& vgg, torch::optim::Optimizer& opt_g,
                    torch::optim::Optimizer& opt_d, const TrainOptions& opt, const Batch& batch, int64_t step,
                    GradientAverager* sync = nullptr, const DataConsistency* consistency = nullptr);

class GanTrainer {
 public:
  GanTrainer(Generator generator, Discriminator discriminator, Vgg16Features vgg,
             std::shared_ptr<const PairSource> train, std::vector<Sample> val, TrainOptions options,
             ModelIdentity identity);
  // Data-parallel: rank 0's weights are broadcast, gradients averaged every step, batches sharded
  // by rank; only rank 0 validates and writes files. Call before resume() and run().
  void set_distributed(GradientAverager* collectives);
  // Continues from a checkpoint written by an earlier run with the same config; the best PSNR is
  // best.ckpt's (next to it; `best_psnr` when the caller has read that file already, so it is read
  // once), and model.flatnet is rewritten from the restored weights. Returns one line saying what
  // was restored.
  std::string resume(const std::filesystem::path& checkpoint, std::optional<double> best_psnr = std::nullopt);
  // The id of a new run, recorded in every checkpoint it writes (a resume keeps the checkpoint's).
  void set_run_id(std::string id) { state_.run_id = std::move(id); }
  const std::string& run_id() const { return state_.run_id; }
  // The weights that are validated and exported: the moving average when train.ema_decay > 0.
  Generator& exported();
  // Co-design (train/codesign.hpp): the training source gives scenes (SimulatedPairs without a
  // rig), each batch is captured through `camera` in the graph and its codes learn with the
  // network until codes.freeze_at; checkpoints hold them; every checkpoint writes OUT/camera/
  // (codes.mat and the camera they make, with `geometry`'s preprocessing). Validation scenes are
  // captured through the current codes with fixed noise. Call before set_distributed(), resume()
  // and run().
  void set_learned_camera(CodePairCamera camera, CameraConfig geometry);
  // model.consistency: the data-consistency layer through the camera's calibration, in every
  // training step and validation. Whole scenes only (train.crop 0), no co-design (run_experiment
  // checks both before anything is written). Call before run().
  void set_consistency(std::shared_ptr<const DataConsistency> consistency) { consistency_ = std::move(consistency); }
  // Stops after the current step and writes a checkpoint when interrupted() (core/util.hpp).
  TrainSummary run();

 private:
  // What a run adds up between log rows, and the batch-norm buffers a skipped step puts back.
  struct StepTally {
    StepLosses sums;
    int64_t steps = 0;
    std::vector<torch::Tensor> statistics;
  };
  void train_step(BatchLoader& loader, int64_t step, StepTally& tally);
  std::string log_row(int64_t done, int64_t first_step, StepTally& tally);
  bool codes_frozen(int64_t step) const;
  // The batch's planes through the learned camera; with a graph to its codes while they learn.
  torch::Tensor capture_batch(const Batch& batch, int64_t step);
  void step_codes(int64_t step);  // after gan_step: the throughput penalty, then Adam on the codes
  CheckpointCamera checkpoint_camera();
  void set_learning_rates(int64_t step);
  void checkpoint_and_validate(TrainSummary& summary);
  // latest.ckpt alone (train.save_minutes): the state a resume continues from, not validated; best.ckpt
  // and model.flatnet stay the last validation's (a resume rewrites model.flatnet from it).
  void save_resumable();
  // train.bn_refresh: the exported weights' batch-norm statistics re-estimated before validation.
  void refresh_exported_statistics();
  static constexpr uint64_t kRefreshSeedOffset = 0x5EED;  // its batches' seed, beside the training's
  // What model.flatnet records: the run's identity with its steps, time and best validation PSNR.
  ModelIdentity exported_identity() const;
  void keep_model();  // RUN/kept/step<N>.flatnet (train.keep_every)
  // Training time in all: the checkpoint's record plus this run's time so far.
  double trained_seconds() const { return loop_ ? loop_->trained_seconds() : state_.train_seconds; }
  const TrainingLoop* loop_ = nullptr;   // while run() runs: its clock
  std::optional<CsvLog> log_, val_log_;  // log.csv, val.csv (the writer's)

  Generator g_;
  Discriminator d_;
  Vgg16Features vgg_;
  std::shared_ptr<const PairSource> train_;
  std::vector<Sample> val_;
  TrainOptions opt_;
  ModelIdentity identity_;  // written into every checkpoint and model file
  std::unique_ptr<torch::optim::Adam> opt_g_, opt_d_;
  std::unique_ptr<WeightAverage> ema_;
  TrainState state_;
  GradientAverager* sync_ = nullptr;
  CodePairCamera camera_{nullptr};  // co-design only
  std::optional<Rig> frozen_rig_;   // its camera once the codes are frozen (built once)
  std::unique_ptr<torch::optim::Adam> opt_camera_;
  CameraConfig camera_geometry_;
  std::shared_ptr<const DataConsistency> consistency_;  // model.consistency only
};

}  // namespace flatnet
