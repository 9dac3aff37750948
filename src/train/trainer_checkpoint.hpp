#pragma once
// The checkpoint of a small trainer (the mask trainer, the code-pair trainer) in one safetensors
// file, `OUT/latest.ckpt`: its named parameters, their optimiser's state (SGD's momentum or Adam's
// moments, by parameter name: LibTorch keys its state by address, which means nothing in a file),
// the step, the seconds trained, and whatever else the trainer adds (its data order's generator).
// Loading one is reading data; every tensor is checked against the live parameter (shape, finite)
// before it is used, and a file of another trainer, another optimiser or another size is refused
// with the file's name and what differs. (FlatNet's GAN trainer has its own, nn/model_file.)
#include <cstdint>
#include <filesystem>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include <torch/torch.h>

#include "io/safetensors.hpp"

namespace flatnet {

struct TrainerState {
  std::vector<std::pair<std::string, torch::Tensor>> params;  // name -> the live parameter
  torch::optim::Optimizer* optimizer = nullptr;
  std::string optimizer_kind;  // sgd | adam
  std::string format;          // the trainer's file format name, e.g. "flatnet-mask-checkpoint"
  std::string size_hint;       // what a parameter of another shape means ("another mask.rank?")
  std::string run_id;          // the run that writes it (train/run_id.hpp); "" writes none
};

inline std::filesystem::path trainer_checkpoint_path(const std::filesystem::path& out) { return out / "latest.ckpt"; }
// Whether the run folder `out` holds a checkpoint to resume.
inline bool has_trainer_checkpoint(const std::filesystem::path& out) {
  return std::filesystem::exists(trainer_checkpoint_path(out));
}

// Written atomically. `extra` tensors and `metadata` are the trainer's own.
void write_trainer_checkpoint(const std::filesystem::path& path, const TrainerState& state, int64_t step,
                              double seconds, const std::map<std::string, std::string>& metadata = {},
                              const std::vector<std::pair<std::string, torch::Tensor>>& extra = {});

struct RestoredTraining {
  int64_t step = 0;
  double seconds = 0;
  std::string run_id;  // the run that wrote it; "" in files from before run ids
  SafeTensors file;    // for the trainer's own extras
};

// Restores the parameters and the optimiser's state of `state` from `path` (a missing file: "nothing
// to resume").
RestoredTraining read_trainer_checkpoint(const std::filesystem::path& path, const TrainerState& state);

}  // namespace flatnet
