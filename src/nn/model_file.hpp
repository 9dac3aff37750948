#pragma once
// What a trained model is on disk.
//  - Model file (`flatnet infer --model`): one self-contained safetensors file with the generator's
//    weights, the merged config that describes its architecture, and the camera preprocessing it
//    was trained for. Format tag "flatnet-model", version 2 (version 1, a TorchScript archive, is
//    read as data and rewritten by `flatnet export --model OLD --out NEW`). Nothing loaded runs code.
//  - Checkpoint (`flatnet train`, resumable): the same plus the discriminator, both optimisers,
//    the step, the best validation PSNR and the RNG state. Format tag "flatnet-checkpoint".
//  - State dict (`flatnet export --state-dict`, `flatnet import`): a torch.save-compatible dict of
//    tensors with FlatNet-sep's parameter names (PhiL, PhiR, bn.*, inc.*, down1.*, ..., outc.*).
#include <filesystem>
#include <string>

#include "io/camera_config.hpp"
#include "nn/generator.hpp"
#include "nn/losses.hpp"
#include "io/config.hpp"
#include "io/options.hpp"

namespace flatnet {

// The generator a config describes for a camera. With `initialise`, the first stage gets its
// initial weights (model.inversion.init; the calibration for transpose and naive models);
// without, only the shapes (weights come from a file).
GeneratorOptions generator_options(const Config& config, const CameraConfig& camera, bool initialise);
// The enhancers' option tables (io/options.hpp), keys under model.unet., model.dncnn., model.rcan.
// and model.nafnet.; generator_options reads through them.
const std::vector<OptionField<UNetOptions>>& unet_fields();
const std::vector<OptionField<DnCNNOptions>>& dncnn_fields();
const std::vector<OptionField<RCANOptions>>& rcan_fields();
const std::vector<OptionField<NAFNetOptions>>& nafnet_fields();
DiscriminatorOptions discriminator_options(const Config& config);

// Where a model file came from, beside its weights (metadata strings; empty when not known, as in
// files from before 2026-11-24 or imported state dicts). `flatnet info` prints them.
struct Provenance {
  std::string trained_steps;   // optimiser steps, "12000"
  std::string train_seconds;   // wall-clock training time, "14400.5"
  std::string best_val_psnr;   // the run's best validation PSNR (dB; validation split, not held-out)
  std::string written_at;      // UTC, ISO 8601: "2026-11-24T05:52:00Z"
  std::string written_on;      // the CPU that wrote it ("AMD EPYC ...; avx512f avx512_bf16")
  std::string source;          // what it was made from: "checkpoint latest.ckpt (moving average)"
  std::string scores;          // held-out scores, JSON {"SET": {"images": N, "psnr": ..., ...}}
};
// Provenance's fields with their metadata keys, in the order `flatnet info` prints them.
std::vector<std::pair<std::string, std::string Provenance::*>> provenance_fields();

struct ModelFile {
  Generator generator{nullptr};
  Config config;
  CameraConfig camera;
  int format_version = 2;  // 1: a TorchScript archive from before 2026-11 (read as data)
  Provenance provenance;
};

// What a model file or checkpoint records beside its weights: the merged config that describes the
// architecture (YAML text, as Config::to_yaml writes it) and the camera preprocessing. Trainers
// carry this, not the Config object.
struct ModelIdentity {
  std::string config_yaml;
  CameraConfig camera;
  Provenance provenance;  // written_at and written_on are filled in when a file is written
};
ModelIdentity model_identity(const Config& config, const CameraConfig& camera);

void save_model_file(const std::filesystem::path& path, Generator& generator, const ModelIdentity& identity);
void save_model_file(const std::filesystem::path& path, Generator& generator, const Config& config,
                     const CameraConfig& camera, const Provenance& provenance = {});
// Errors (naming the file): not a flatnet archive, a checkpoint where a model is expected (or the
// reverse), a newer format version, weights missing or of the wrong shape.
ModelFile load_model_file(const std::filesystem::path& path);

struct TrainState {
  int64_t step = 0;         // optimiser steps done
  double best_psnr = -1e9;  // best validation PSNR so far
  torch::Tensor rng_state;  // the default CPU generator's state
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
// Whether a flatnet file (format 1 or 2) is a training checkpoint rather than a model file.
bool is_checkpoint_file(const std::filesystem::path& path);
// 2 for a safetensors model file or checkpoint, 1 for a format-1 TorchScript archive, 0 otherwise.
int model_file_version(const std::filesystem::path& path);
// What a checkpoint holds besides its tensors, from one read: the config and camera (to rebuild the
// networks before load_checkpoint) and the run that wrote it.
struct CheckpointSettings {
  Config config;
  CameraConfig camera;
  std::string run_id;  // 16 hex digits; "" for files written before run ids
};
CheckpointSettings checkpoint_settings(const std::filesystem::path& path);
// `ema` is filled from the checkpoint's average when it has one, else from its generator.
// A checkpoint without a camera is refused when `camera` is given (and the reverse).
TrainState load_checkpoint(const std::filesystem::path& path, Generator& g, Discriminator& d, torch::optim::Adam& opt_g,
                           torch::optim::Adam& opt_d, Generator* ema = nullptr, const CheckpointCamera& camera = {});
// A checkpoint's generator as a model file (what `flatnet export` does): the moving average of
// the weights when the run kept one, else the live weights. `used_average` tells which.
ModelFile model_from_checkpoint(const std::filesystem::path& path, bool* used_average = nullptr);

// Copies a model file's generator weights into `g` (`flatnet train --init-from`): every tensor
// must exist with the same shape, else an error naming the file, the tensor and both shapes.
// One exception: a model without model.level_input into a generator with it; the enhancer's first
// convolution gets zero weights for the level channels (the same function to begin with).
// With GeneratorPart::enhancer, only the enhancer and the batch norm after the first stage are
// copied (`--reinit inversion`): the first stage (inversion or Tikhonov layer) keeps the values `g`
// was built with (this camera's), and may differ in shape from the file's.
enum class GeneratorPart { all, enhancer };
void init_generator_from(const std::filesystem::path& model, Generator& g, GeneratorPart part = GeneratorPart::all);

// FlatNet-sep name of one of our parameter names ("inversion.PhiL" -> "PhiL",
// "enhancer.inc.conv.conv.0.weight" -> "inc.conv.conv.0.weight").
std::string flatnet_name(const std::string& ours);

// The first stage for a new camera that reproduces a trained model's (`--reinit inversion` with
// model.inversion.init transfer): per Bayer channel, W_new = argmin ||W^T P_new - W_old^T P_old||^2
// + lambda s_max^2 ||W||^2 = U diag(s / (s^2 + lambda s_max^2)) V^T (W_old^T P_old)^T for
// P_new = U diag(s) V^T, and the same for W2 with Q. The enhancer then sees, through the new
// camera, the intermediate image it was trained on (W_old^T P_old X Q_old^T W2_old). `source`:
// the trained model file; its camera's calibration (P_old, Q_old) and this camera's, {4,m,N} each.
struct CalibrationPair {
  torch::Tensor P_old, Q_old, P_new, Q_new;
};
void transfer_inversion(const std::filesystem::path& source, const CalibrationPair& calibrations, double lambda,
                        Generator& g);
// torch.save(generator.state_dict()) as PyTorch writes it (an OrderedDict in the zip container),
// or FlatNet's checkpoint layout {'gen_state_dict': OrderedDict} that its main.py loads.
enum class StateDictLayout { state_dict, flatnet_checkpoint };
void export_state_dict(const std::filesystem::path& path, Generator& generator,
                       StateDictLayout layout = StateDictLayout::state_dict);
// Reads a generator state dict from any torch.save file (zip or legacy container, io/torch_file):
// a plain dict or an OrderedDict of tensors, FlatNet's checkpoint ({'gen_state_dict': ...,
// optimiser states, ...}), or one under 'generator', 'state_dict' or 'model'; DataParallel's
// "module." prefixes are dropped. Every tensor the model needs must be present, finite, with the
// right shape, else an error naming the file and the tensor.
struct ImportReport {
  std::string source;               // where the state dict was found ("'gen_state_dict'", ...)
  bool data_parallel = false;       // names carried DataParallel's "module." prefix
  int64_t used = 0;                 // tensors loaded into the model
  std::vector<std::string> unused;  // tensors of that dict the model has no place for
};
ImportReport import_state_dict(const std::filesystem::path& path, Generator& generator);

}  // namespace flatnet
