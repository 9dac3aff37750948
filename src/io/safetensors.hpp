#pragma once
// safetensors: the field's format for shared weights (https://github.com/huggingface/safetensors),
// which flatnet's model files and checkpoints use. Loading one is reading data, never running code,
// in flatnet as in Python (`safetensors.torch.load_file`), unlike a pickle or a TorchScript archive.
//
// Layout (the format's specification):
//   8 bytes   N, unsigned little-endian: the header's length
//   N bytes   UTF-8 JSON object: {"NAME": {"dtype": "F32", "shape": [2, 3], "data_offsets": [BEGIN, END]},
//             ..., "__metadata__": {"key": "string value", ...}}, padded with spaces
//   the rest  the byte buffer: each tensor's little-endian elements, C order, at [BEGIN, END)
//
// The reader believes nothing the file claims before it is checked against the bytes present and
// against limits: the header's length and depth, duplicate names, element counts (overflow-checked),
// offsets that must tile the buffer exactly (no holes, no overlaps, no bytes past the end).
#include <cstdint>
#include <filesystem>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include <torch/torch.h>

namespace flatnet {

struct SafeTensors {
  std::map<std::string, std::string> metadata;                 // "__metadata__"
  std::vector<std::pair<std::string, torch::Tensor>> tensors;  // in the buffer's order

  // The tensor of that name, or null.
  const torch::Tensor* find(const std::string& name) const;
  // The metadata string of that key, or an Error naming `where` and the key.
  const std::string& meta(const std::string& key, const std::filesystem::path& where) const;
};

struct SafeTensorsLimits {
  uint64_t max_header_bytes = 100u << 20;  // the specification's own limit (100 MB)
  uint64_t max_file_bytes = 16ull << 30;   // 16 GiB: far above any flatnet model
  int64_t max_tensors = 100000;
  int64_t max_metadata_keys = 4096;  // flatnet writes ~20; other tools a handful
};

// A flatnet extension inside __metadata__ (other readers ignore it): zlib's CRC-32 of the byte
// buffer, 8 hex digits. Written always; checked, then removed from `metadata`, when present.
constexpr const char* kCrcKey = "data_crc32";

// The file's bytes. Tensors are written contiguous, in the order given; names must be unique and
// non-empty ("__metadata__" is reserved). Types: float32/64, bfloat16, float16, int8..int64, uint8, bool.
std::string safetensors_bytes(const std::vector<std::pair<std::string, torch::Tensor>>& tensors,
                              const std::map<std::string, std::string>& metadata);
// Written atomically (a reader never sees half a file); a full disk is an error naming `path`.
void write_safetensors(const std::filesystem::path& path,
                       const std::vector<std::pair<std::string, torch::Tensor>>& tensors,
                       const std::map<std::string, std::string>& metadata);

// Errors name `path` and what is wrong. `bytes` is the whole file, read by the caller.
SafeTensors parse_safetensors(const std::string& bytes, const std::filesystem::path& path,
                              const SafeTensorsLimits& limits = {});
SafeTensors read_safetensors(const std::filesystem::path& path, const SafeTensorsLimits& limits = {});
// The "__metadata__" strings alone, from the file's first 8 + N bytes, so a file's kind is known
// without reading its weights. The header's length, JSON, nesting, key counts and metadata get
// parse_safetensors's checks; the tensor entries and the buffer are not read (nor is the CRC-32,
// which covers the buffer): loading the file checks them.
std::map<std::string, std::string> read_safetensors_metadata(const std::filesystem::path& path,
                                                             const SafeTensorsLimits& limits = {});

// Whether the bytes start like a safetensors file (a plausible length, then '{').
bool looks_like_safetensors(const std::string& bytes);

}  // namespace flatnet
