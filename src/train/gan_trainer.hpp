#pragma once
// FlatNet's adversarial training (Khan et al. 2019, sec. 4): per batch one discriminator step on
// real images and detached generator outputs, then one generator step on
//   l1 * MSE + l2 * (MSE(relu2_2) + MSE(relu4_3)) + l3 * BCE(D(G(y)), 1),
// Adam for both, learning rates halved every `lr_halve_every` steps. Validation (PSNR, SSIM, a
// sample sheet) and atomic checkpoints (latest.ckpt, best.ckpt, model.flatnet) every `val_every`
// steps; a resumed run continues with the same data order, noise and weights, bit for bit.
#include <atomic>
#include <filesystem>
#include <memory>
#include <vector>

#include "core/camera_config.hpp"
#include "nn/generator.hpp"
#include "nn/losses.hpp"
#include "train/config.hpp"
#include "train/data.hpp"
#include "train/model_file.hpp"

namespace flatnet {

struct TrainOptions {
  int64_t iterations = 20000;
  int64_t batch = 4;
  double lr = 1e-4, lr_discriminator = 1e-4, lr_inversion_scale = 1.0;
  int64_t lr_halve_every = 5000;
  int64_t discriminator_warmup = 0;
  double noise_augment = 0.003;
  uint64_t seed = 0;
  int workers = 1;
  int64_t val_every = 500, log_every = 10;
  double w_mse = 1.0, w_perceptual = 1.2, w_adversarial = 0.6;
  double real_label_min = 0.7, fake_label_max = 0.3;
  bool channels_last = true;   // exact speed-ups (InferenceLevers): NHWC activations,
  bool gemm_upsample = true;   // transposed convolutions as GEMMs
  int64_t check_sync_every = 0;  // distributed: verify bit-identical parameters every N steps (0: never)
  std::filesystem::path out;  // run folder: latest.ckpt, best.ckpt, model.flatnet, log.csv, val.csv, samples.png
  bool progress = true;
};

struct TrainSummary {
  int64_t first_step = 0, last_step = 0;
  double best_psnr = 0, best_ssim = 0, last_psnr = 0, last_ssim = 0;
  double seconds = 0, steps_per_s = 0, loader_wait_s = 0;
};

struct ValidationResult {
  double psnr = 0, ssim = 0;
};

// Runs the generator over samples (eval mode, batches of `batch`); returns means and, when
// `sheet` is set, writes a contact sheet of the first `sheet_rows` (truth | output).
ValidationResult validate(Generator& generator, const std::vector<Sample>& samples, int64_t batch,
                          const std::filesystem::path& sheet = {}, int sheet_rows = 4);

struct StepLosses {
  double loss = 0, mse = 0, perceptual = 0, adversarial = 0, discriminator = 0;
};

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
// `sync`, gradients are averaged across processes before each optimiser step. Throws on a
// non-finite loss before any parameter changes.
StepLosses gan_step(Generator& g, Discriminator& d, Vgg16Features& vgg, torch::optim::Optimizer& opt_g,
                    torch::optim::Optimizer& opt_d, const TrainOptions& opt, const Batch& batch, int64_t step,
                    GradientAverager* sync = nullptr);

class GanTrainer {
 public:
  GanTrainer(Generator generator, Discriminator discriminator, Vgg16Features vgg,
             std::shared_ptr<const PairSource> train, std::vector<Sample> val, TrainOptions options,
             Config config, CameraConfig camera);
  // Data-parallel: rank 0's weights are broadcast, gradients averaged every step, batches sharded
  // by rank; only rank 0 validates and writes files. Call before resume() and run().
  void set_distributed(GradientAverager* collectives);
  // Continues from a checkpoint written by an earlier run with the same config.
  void resume(const std::filesystem::path& checkpoint);
  // Stops after the current step and writes a checkpoint when interrupted() (core/util.hpp).
  TrainSummary run();

 private:
  void set_learning_rates(int64_t step);
  void checkpoint_and_validate(TrainSummary& summary);

  Generator g_;
  Discriminator d_;
  Vgg16Features vgg_;
  std::shared_ptr<const PairSource> train_;
  std::vector<Sample> val_;
  TrainOptions opt_;
  Config config_;
  CameraConfig camera_;
  std::unique_ptr<torch::optim::Adam> opt_g_, opt_d_;
  TrainState state_;
  GradientAverager* sync_ = nullptr;
};

}  // namespace flatnet
