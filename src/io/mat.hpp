#pragma once
// MATLAB .mat files (v5; v7.3 when matio was built with HDF5) through matio. A v7.3 file is HDF5,
// whose parser is not safe on damaged files: it is read whole in an isolated child process
// (io/isolated_reader.hpp), every variable checked against the reader's bound there.
// MATLAB stores arrays column-major; these functions return and take row-major torch tensors
// with MATLAB's shape (a 500x256 variable becomes a {500,256} tensor, a 500x256x4 one {500,256,4}).
#include <filesystem>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "io/mat_check.hpp"

namespace flatnet {

enum class MatVersion { v5, v73 };

// Reads numeric variables (double, single or integer classes) as float64 tensors.
class MatReader {
 public:
  // No variable may hold more than `max_variable_bytes` (its claim checked before it is read or
  // inflated, v5 and v7.3 alike): a reader that knows its sizes (a calibration for a camera) says so.
  explicit MatReader(const std::filesystem::path& path, uint64_t max_variable_bytes = kMaxMatVariableBytes);
  ~MatReader();
  MatReader(const MatReader&) = delete;
  MatReader& operator=(const MatReader&) = delete;

  bool has(const std::string& name) const;
  std::vector<std::string> names() const;
  // Errors "<file>: missing variable 'name'" or "...: variable 'name' is HxW, expected ...".
  torch::Tensor read(const std::string& name) const;
  torch::Tensor read(const std::string& name, const std::vector<int64_t>& expected_shape) const;
  double read_scalar(const std::string& name) const;
  const std::filesystem::path& path() const { return path_; }

  struct Variables;  // a v7.3 file's variables, as its isolated reader handed them back (mat.cpp)

 private:
  std::filesystem::path path_;
  uint64_t max_variable_bytes_;
  void* mat_ = nullptr;  // a v5 file, open in matio
  std::unique_ptr<const Variables> v73_;
  [[noreturn]] void missing(const std::string& name) const;
};

// Writes float64 variables. The file appears atomically when write() returns.
void write_mat(const std::filesystem::path& path, const std::map<std::string, torch::Tensor>& vars,
               MatVersion version = MatVersion::v5);

}  // namespace flatnet
