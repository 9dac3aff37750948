#pragma once
// What a stored file (nn/stored_file.hpp) says of the model it holds, for model files and checkpoints;
// internal to nn: its header metadata, provenance, typed spec and camera, and the generator itself.
#include <filesystem>
#include <map>
#include <string>
#include <utility>

#include "nn/model_identity.hpp"
#include "nn/stored_file.hpp"

namespace flatnet::detail {

// The metadata every file of `format` starts with (written_at and written_on filled in now).
std::map<std::string, std::string> header(const std::string& format, const ModelIdentity& identity);
Provenance provenance_of(const Stored& s);

// What the file says its generator is: its typed spec (files from before the spec: their embedded
// config, converted) and its camera, both checked against the weights it holds before any network
// of that size is built.
std::pair<ModelSpec, CameraConfig> stored_model(const Stored& s, const std::filesystem::path& path);
// The generator (with its spec, recipe and camera) from a model file or a checkpoint; from a
// checkpoint that kept a moving average of the weights, the average.
ModelFile read_generator(const Stored& s, const std::filesystem::path& path, bool* used_average = nullptr);

}  // namespace flatnet::detail
