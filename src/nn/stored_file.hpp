#pragma once
// The container that model files (nn/model_file.hpp) and checkpoints (nn/checkpoint.hpp) share;
// internal to nn, and knows nothing of the model it holds (nn/model_record.hpp reads that). Format 2 is a safetensors
// file: every tensor under a prefix ("generator.", "generator_ema.", "discriminator.", "optimizer_generator.",
// "optimizer_discriminator."), and strings in __metadata__: format, format_version, model_spec (YAML, the typed
// generator spec), config (YAML: the training recipe, kept as a record), camera (YAML), the provenance and, for
// checkpoints, step, best_psnr, run_id and each optimiser's parameter groups (JSON). Python reads it
// with `safetensors.torch.load_file` (no code runs), or with nothing but json and struct.
// Format 1 (before 2026-11) was a TorchScript archive; it is still read, as data
// (read_torchscript_archive), never through LibTorch's loader, which would run its code.
#include <filesystem>
#include <functional>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include <torch/torch.h>

namespace flatnet::detail {

constexpr const char* kModelFormat = "flatnet-model";
constexpr const char* kCheckpointFormat = "flatnet-checkpoint";
constexpr int kFormatVersion = 2;

struct Stored {
  std::map<std::string, std::string> meta;
  std::map<std::string, torch::Tensor> tensors;
  int version = kFormatVersion;

  // The metadata string `key`; a file without it is "not a flatnet file".
  const std::string& text(const std::string& key, const std::filesystem::path& path) const;
  // Tensors under "<prefix>." with the prefix removed.
  std::map<std::string, torch::Tensor> under(const std::string& prefix) const;
};

std::string format_number(double v);  // 17 significant digits
// A format-1 archive's top-level values as format 2 names them.
Stored read_format1(const std::filesystem::path& path);
// A model file or checkpoint of `expected_format`, checked: the format, a version this flatnet reads.
Stored read_stored(const std::filesystem::path& path, const std::string& expected_format);

// Fills every parameter and buffer of `m` with fetch(name, is_buffer), checking shapes and
// finiteness; errors about `where` call a tensor "<label> '<its name in the file>'".
void fill_module(
    torch::nn::Module& m, const std::filesystem::path& where, const std::string& label,
    const std::function<torch::Tensor(const std::string&, bool)>& fetch,
    const std::function<std::string(const std::string&)>& name_in_file = [](const std::string& n) { return n; });
// Every parameter and buffer of `m`, prefixed, in the module's order.
void add_module(std::vector<std::pair<std::string, torch::Tensor>>& out, const std::string& prefix,
                torch::nn::Module& m);
void load_module(const Stored& s, const std::string& key, torch::nn::Module& m, const std::filesystem::path& where);

}  // namespace flatnet::detail
