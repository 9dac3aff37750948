#pragma once
// What a trained model is on disk.
//  - Model file (`flatnet infer --model`): one self-contained safetensors file with the generator's
//    weights, its typed spec (nn/model_spec: architecture, widths, inversion), the camera
//    preprocessing it was trained for, and the training config as a record. It reads the same with
//    no configs folder: the spec is not read over today's defaults. Files written before the spec
//    carried their training config instead; its model section is converted when read. Format tag
//    "flatnet-model", version 2 (version 1, a TorchScript archive, is read as data and rewritten by
//    `flatnet export --model OLD --out NEW`). Nothing loaded runs code (nn/stored_file).
//  - Checkpoint (nn/checkpoint.hpp): the same plus the training state.
//  - State dict (`flatnet export --state-dict`, `flatnet import`): a torch.save-compatible dict of
//    tensors with FlatNet-sep's parameter names (PhiL, PhiR, bn.*, inc.*, down1.*, ..., outc.*).
#include <filesystem>
#include <map>
#include <string>

#include "io/camera_config.hpp"
#include "io/config.hpp"
#include "nn/generator.hpp"
#include "nn/model_identity.hpp"
#include "nn/model_spec.hpp"

namespace flatnet {

void save_model_file(const std::filesystem::path& path, Generator& generator, const ModelIdentity& identity);
void save_model_file(const std::filesystem::path& path, Generator& generator, const Config& config,
                     const CameraConfig& camera, const Provenance& provenance = {});
// Errors (naming the file): not a flatnet archive, a checkpoint where a model is expected (or the
// reverse), a newer format version, weights missing or of the wrong shape.
ModelFile load_model_file(const std::filesystem::path& path);

// Whether a flatnet file (format 1 or 2) is a training checkpoint rather than a model file.
bool is_checkpoint_file(const std::filesystem::path& path);
// 2 for a safetensors model file or checkpoint, 1 for a format-1 TorchScript archive, 0 otherwise.
int model_file_version(const std::filesystem::path& path);
// Copies a model file's generator weights into `g` (`flatnet train --init-from`): every tensor
// must exist with the same shape, else an error naming the file, the tensor and both shapes.
// One exception: a model without model.level_input into a generator with it; the enhancer's first
// convolution gets zero weights for the level channels (the same function to begin with).
// With GeneratorPart::enhancer, only the enhancer and the batch norm after the first stage are
// copied (`--reinit inversion`): the first stage (inversion or Tikhonov layer) keeps the values `g`
// was built with (this camera's), and may differ in shape from the file's.
enum class GeneratorPart { all, enhancer };
void init_generator_from(const std::filesystem::path& model, Generator& g, GeneratorPart part = GeneratorPart::all);
// The same from a model file already read (`model` names it in errors).
void init_generator_from(const ModelFile& m, const std::filesystem::path& model, Generator& g,
                         GeneratorPart part = GeneratorPart::all);

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
