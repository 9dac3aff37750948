#pragma once
// What a model is, beside its weights: the types a model file and a checkpoint both record
// (provenance, the typed spec, the camera, the training config) and the generator read with them.
// nn/model_record reads and writes these from a stored file; nn/model_file and nn/checkpoint are the
// formats on disk. Both include this, not each other.
#include <filesystem>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include "io/camera_config.hpp"
#include "io/config.hpp"
#include "nn/generator.hpp"
#include "nn/model_spec.hpp"

namespace flatnet {

// Where a model file came from, beside its weights (metadata strings; empty when not known, as in
// files from before 2026-11-24 or imported state dicts). `flatnet info` prints them.
struct Provenance {
  std::string trained_steps;  // optimiser steps, "12000"
  std::string train_seconds;  // wall-clock training time, "14400.5"
  std::string best_val_psnr;  // the run's best validation PSNR (dB; validation split, not held-out)
  std::string written_at;     // UTC, ISO 8601: "2026-11-24T05:52:00Z"
  std::string written_on;     // the CPU that wrote it ("AMD EPYC ...; avx512f avx512_bf16")
  std::string source;         // what it was made from: "checkpoint latest.ckpt (moving average)"
  std::string scores;         // held-out scores, JSON {"SET": {"images": N, "psnr": ..., ...}}
  // The spec's data-consistency step (model.consistency): kConsistencyTrained when the weights learned
  // with it, kConsistencySetAtExport when `export --data-consistency` added it to weights trained
  // without it; "" when the spec has none.
  std::string consistency;
};
inline constexpr const char* kConsistencyTrained = "trained";
inline constexpr const char* kConsistencySetAtExport = "set at export";
// Provenance::consistency for a model of this spec: the recorded origin, or for a file from before it
// was recorded (2026-12), what its source text says ("... set at export, not trained with").
std::string consistency_origin(const ModelSpec& spec, const Provenance& provenance);
// Provenance's fields with their metadata keys, in the order `flatnet info` prints them.
std::vector<std::pair<std::string, std::string Provenance::*>> provenance_fields();

struct ModelFile {
  Generator generator{nullptr};
  ModelSpec spec;       // what the weights are
  CameraConfig camera;  // the preprocessing it was trained for
  std::string recipe;   // the training config as recorded (YAML; a record, never read over defaults)
  std::map<std::string, std::string> recipe_values;  // the recipe by dotted key, parsed once when read
  int format_version = 2;                            // 1: a TorchScript archive from before 2026-11 (read as data)
  Provenance provenance;

  // A setting of the recorded training config as text (its data.camera -> the camera file's
  // path); "" when the file does not record it.
  std::string recorded(const std::string& key) const;
  // The camera file the recorded training config names (data.camera); empty when not recorded.
  std::filesystem::path recorded_camera() const;
};

// What a model file or checkpoint records beside its weights: the training config (YAML text, as
// Config::to_yaml writes it; a checkpoint resumes from it, a model file keeps it as a record), the
// generator's spec and the camera preprocessing. Trainers carry this, not the Config object.
struct ModelIdentity {
  std::string config_yaml;
  ModelSpec spec;
  CameraConfig camera;
  Provenance provenance;  // written_at and written_on are filled in when a file is written
};
ModelIdentity model_identity(const Config& config, const CameraConfig& camera);
ModelIdentity model_identity(const ModelFile& model);  // to write it again (export)

}  // namespace flatnet
