#pragma once
// A training checkpoint (`flatnet train`, resumable; format tag "flatnet-checkpoint"): a model
// file's contents (nn/model_file.hpp) plus the discriminator, both optimisers, the step, the best
// validation PSNR, the run id and the RNG state, and the full training config (a resume rebuilds
// the run from it, over this flatnet's defaults).
#include <filesystem>
#include <string>

#include "nn/model_file.hpp"

namespace flatnet {

struct TrainState {
  int64_t step = 0;                 // optimiser steps done
  double best_psnr = -1e9;          // best validation PSNR so far
  torch::Tensor rng_state;          // the default CPU generator's state
  bool optimizers_restored = true;  // false after loading a format-1 checkpoint (moments start afresh)
  double train_seconds = 0;         // wall-clock training time so far (train.minutes counts it)
  std::string run_id;               // the run that wrote it (16 hex digits; "" in older files)
};

// A co-design run's learned camera (train/codesign.hpp): its parameters ("camera.") and their
// optimiser ("optimizer_camera.") travel in the checkpoint; both null for other runs.
struct CheckpointCamera {
  torch::nn::Module* module = nullptr;
  torch::optim::Adam* optimizer = nullptr;
};
// `ema`, when given, is the moving average of the generator's weights (saved as "generator_ema").
void save_checkpoint(const std::filesystem::path& path, Generator& g, Discriminator& d, torch::optim::Adam& opt_g,
                     torch::optim::Adam& opt_d, const TrainState& state, const ModelIdentity& identity,
                     Generator* ema = nullptr, const CheckpointCamera& camera = {});
// The best validation PSNR a checkpoint records (best.ckpt: the PSNR of the weights it holds).
double checkpoint_best_psnr(const std::filesystem::path& path);
// What a checkpoint holds besides its tensors, from one read: the config and camera (to rebuild the
// networks before load_checkpoint) and the run that wrote it.
struct CheckpointSettings {
  Config config;
  CameraConfig camera;
  std::string run_id;  // 16 hex digits; "" for files written before run ids
  double best_psnr;    // the best validation PSNR it records (checked to be a number)
};
CheckpointSettings checkpoint_settings(const std::filesystem::path& path);
// `ema` is filled from the checkpoint's average when it has one, else from its generator.
// A checkpoint without a camera is refused when `camera` is given (and the reverse).
TrainState load_checkpoint(const std::filesystem::path& path, Generator& g, Discriminator& d, torch::optim::Adam& opt_g,
                           torch::optim::Adam& opt_d, Generator* ema = nullptr, const CheckpointCamera& camera = {});
// A checkpoint's generator as a model file (what `flatnet export` does): the moving average of
// the weights when the run kept one, else the live weights. `used_average` tells which.
ModelFile model_from_checkpoint(const std::filesystem::path& path, bool* used_average = nullptr);
// A model file or a checkpoint (its moving average when it kept one) as a model.
ModelFile load_trained_model(const std::filesystem::path& path);

// The mean of several trained models' weights (`flatnet export --average-of`): checkpoint averaging
// along one run's low-learning-rate end, as stochastic weight averaging does (Izmailov et al.,
// UAI 2018), or a "model soup" of fine-tunings from one start (Wortsman et al., ICML 2022). Each
// parameter and floating-point buffer (batch-norm running statistics) is the mean over the files,
// summed in double; integer buffers are the last file's. Every file must hold the same model spec
// and camera geometry as the first, else an error naming the file that differs. The result keeps
// the last file's record (recipe, steps, training time, best validation) and names every file as
// its source; held-out scores are dropped (they belong to one file's weights, not the mean).
ModelFile average_models(const std::vector<std::filesystem::path>& paths);

}  // namespace flatnet
