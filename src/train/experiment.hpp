#pragma once
// A FlatNet training run as an experiment describes it: configs/defaults.yaml, an experiment file
// and `--set` overrides (io/config), a run folder, optionally a resumed checkpoint or a model to
// start from, and the data-parallel job. This is where the config becomes option structs
// (TrainOptions, GeneratorOptions, data sources); the trainer below never sees it.
#include <filesystem>
#include <iosfwd>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "io/config.hpp"
#include "nn/model_spec.hpp"
#include "train/data.hpp"
#include "train/distributed.hpp"
#include "train/gan_trainer.hpp"

namespace flatnet {

struct ExperimentOptions {
  std::filesystem::path config;     // experiment file (empty: defaults.yaml alone)
  std::vector<std::string> sets;    // "key=value" overrides, applied last
  std::filesystem::path out;        // run folder
  bool resume = false;              // continue out/latest.ckpt with the run's own config
  bool force = false;               // a fresh run over another run's files: delete them first
  std::filesystem::path init_from;  // start from a model file's generator (fresh optimisers)
  bool reinit_inversion = false;    // with init_from: keep the enhancer, the first stage afresh for this camera
  // model.inversion.init transfer: the camera the init_from model was trained for (its calibration);
  // empty: the model's own data.camera.
  std::filesystem::path source_camera;
  DistributedOptions distributed;  // world size 1: a single process
  std::ostream* log = nullptr;     // progress lines (default: std::cerr)
};

struct ExperimentResult {
  TrainSummary summary;
  bool writer = true;  // rank 0: the process that validates and writes files
};

// Estimated bytes one training sample needs (activations for the backward pass and their
// gradients); run_experiment refuses a batch whose estimate exceeds 90 % of the available memory.
double training_bytes_per_sample(const ModelSpec& model, int64_t crop, const CameraConfig& camera);

// Everything that can fail on bad input (config keys and ranges, the camera, VGG weights, data)
// is checked before anything is written. Stops early, with a checkpoint, when interrupted().
ExperimentResult run_experiment(const ExperimentOptions& options);

// The translations the run makes (exposed for tests): train.*, loss.* and discriminator.* keys ->
// TrainOptions (ranges checked, naming the key); data.* -> the training and validation sources.
TrainOptions train_options(const Config& config, const std::filesystem::path& out);
std::pair<std::shared_ptr<const PairSource>, std::shared_ptr<const PairSource>> data_sources(
    const Config& config, const CameraConfig& camera);
// codes.* -> the co-design camera's options (codes.learn; needs data.source simulate and the
// reference camera's scene size).
CodesignOptions codesign_options(const Config& config, const CameraConfig& camera);

}  // namespace flatnet
