#pragma once
// Reading files written by Python's torch.save, without Python and without executing anything.
//
// Two containers (torch/serialization.py):
//  - zip (PyTorch >= 1.6): ARCHIVE/data.pkl holds the pickled object; each tensor storage is the
//    record ARCHIVE/data/KEY, raw little-endian elements.
//  - legacy (before 1.6, `_use_new_zipfile_serialization=False`): five things one after the
//    other: pickled magic number 0x1950a86a20f9469cfc6c, protocol 1001, sys info, the object,
//    the sorted storage keys; then per key an int64 element count and the raw elements.
// The object pickle (protocols 2-5) may name only an allow-list of globals: OrderedDict, the
// tensor rebuilders of torch._utils, torch.Size and the typed storages. Anything else (a class, a
// function that could run code) is refused with an error naming it.
#include <filesystem>
#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include <torch/torch.h>

namespace flatnet {

struct PyValue;
using PyRef = std::shared_ptr<PyValue>;

// The part of Python's object model a torch.save file uses.
struct PyValue {
  enum class Kind { none, boolean, integer, real, string, bytes, list, tuple, dict, tensor, storage, global };
  Kind kind = Kind::none;
  bool boolean = false;
  int64_t integer = 0;
  double real = 0;
  std::string text;                              // string, bytes, global ("module.name"), storage key
  std::vector<PyRef> items;                      // list, tuple
  std::vector<std::pair<PyRef, PyRef>> entries;  // dict, in insertion order (OrderedDict or dict)
  torch::Tensor tensor;                          // tensor: float types as float32 (a storage names its key in text)
  // The unpickler's bookkeeping (limits against hostile files): nesting below this value, values
  // in its fully expanded tree, and whether it sits inside another value (then it may not change).
  int height = 1;
  uint64_t expanded = 1;
  bool frozen = false;

  bool is_dict() const { return kind == Kind::dict; }
  // The value at a string key of a dict, or null.
  PyRef get(const std::string& key) const;
  std::string describe() const;  // "dict", "tensor {2,3}", ... for messages
};

// Checks every entry of a zip file (torch.save's container, flatnet's model files and
// checkpoints) against the CRC-32 its central directory records: LibTorch's reader does not, so a
// damaged block would load as wrong weights. Returns false if the file is not a zip; throws an
// Error naming the file and the entry when one is damaged or cut short.
bool verify_zip_crcs(const std::filesystem::path& path);

// The object a torch.save file holds. Errors name the file: not a torch.save file, truncated,
// an unknown opcode, a refused global, a missing storage record.
PyRef read_torch_file(const std::filesystem::path& path);

// The object a TorchScript archive (torch.jit.save, LibTorch's OutputArchive: flatnet's model files
// before format 2) pickles, read as data: each `__torch__...Module` becomes the dict of its
// attributes (parameters, buffers, submodules, strings). Nothing in the archive's code/ is run or
// even read, so a module with a hostile __setstate__ is only a dict here.
PyRef read_torchscript_archive(const std::filesystem::path& path);

// A TorchScript archive's top level in one call: read_torchscript_archive, its string-keyed entries
// sorted by kind (flatnet's format-1 model files and checkpoints hold nothing else). A nested dict's
// tensors keep tensors_in's joined keys; entries of other kinds are left out.
struct ArchiveTopLevel {
  std::map<std::string, std::string> text;
  std::map<std::string, int64_t> integers;
  std::map<std::string, double> reals;
  std::map<std::string, torch::Tensor> tensors;
  std::map<std::string, std::map<std::string, torch::Tensor>> tensor_dicts;
};
ArchiveTopLevel read_archive_top_level(const std::filesystem::path& path);

// Writes tensors as Python's torch.save(OrderedDict) does (zip container, pickle protocol 2,
// _rebuild_tensor_v2 over one storage per tensor), so torch.load and load_state_dict read it.
// With `wrap_key`, the OrderedDict sits in a dict under that key (FlatNet's {'gen_state_dict': ...}).
void save_torch_state_dict(const std::filesystem::path& path,
                           const std::vector<std::pair<std::string, torch::Tensor>>& tensors,
                           const std::string& wrap_key = "");

// The tensors of a (nested) dict, with keys joined by "." (a nested dict's own key first).
// Non-tensor values are skipped.
std::vector<std::pair<std::string, torch::Tensor>> tensors_in(const PyValue& dict);

}  // namespace flatnet
