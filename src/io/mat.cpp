#include "io/mat.hpp"

#include <algorithm>

#include <H5Epublic.h>
#include <matio.h>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/mat_check.hpp"

namespace flatnet {

namespace {

std::string shape_string(const std::vector<int64_t>& s) {
  std::string out;
  for (size_t i = 0; i < s.size(); ++i) out += (i ? "x" : "") + std::to_string(s[i]);
  return out;
}

// MATLAB data is column-major with dims d0..dk: reading it as row-major gives the reversed shape;
// permuting the axes back yields MATLAB's indexing (a(i,j) == t[i][j]).
torch::Tensor from_column_major(const torch::Tensor& flat, const std::vector<int64_t>& dims) {
  std::vector<int64_t> reversed(dims.rbegin(), dims.rend());
  std::vector<int64_t> perm;
  for (int64_t i = static_cast<int64_t>(dims.size()) - 1; i >= 0; --i) perm.push_back(i);
  return flat.reshape(reversed).permute(perm).contiguous();
}

torch::Tensor to_column_major(const torch::Tensor& t) {
  std::vector<int64_t> perm;
  for (int64_t i = t.dim() - 1; i >= 0; --i) perm.push_back(i);
  return t.permute(perm).contiguous();
}

torch::ScalarType torch_type(matio_classes c) {
  switch (c) {
    case MAT_C_DOUBLE:
      return torch::kFloat64;
    case MAT_C_SINGLE:
      return torch::kFloat32;
    case MAT_C_INT8:
      return torch::kInt8;
    case MAT_C_UINT8:
      return torch::kUInt8;
    case MAT_C_INT16:
      return torch::kInt16;
    case MAT_C_INT32:
      return torch::kInt32;
    case MAT_C_INT64:
      return torch::kInt64;
    default:
      return torch::kUInt8;  // unreachable for numeric classes checked below
  }
}

bool is_supported_numeric(matio_classes c) {
  return c == MAT_C_DOUBLE || c == MAT_C_SINGLE || c == MAT_C_INT8 || c == MAT_C_UINT8 || c == MAT_C_INT16 ||
         c == MAT_C_INT32 || c == MAT_C_INT64;
}

uint64_t element_bytes(matio_classes c) {
  switch (c) {
    case MAT_C_DOUBLE:
    case MAT_C_INT64:
    case MAT_C_UINT64:
      return 8;
    case MAT_C_SINGLE:
    case MAT_C_INT32:
    case MAT_C_UINT32:
      return 4;
    case MAT_C_INT16:
    case MAT_C_UINT16:
      return 2;
    default:
      return 1;
  }
}

}  // namespace

// HDF5 prints its error stack to stderr on a damaged v7.3 file; flatnet names the file itself.
void silence_hdf5_errors() {
  static const bool silenced = H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr) >= 0;
  (void)silenced;
}

MatReader::MatReader(const std::filesystem::path& path, uint64_t max_variable_bytes)
    : path_(path), max_variable_bytes_(max_variable_bytes) {
  silence_hdf5_errors();
  // Regular file, sizes and counts checked before matio allocates.
  const auto bytes = read_file_text(path);
  check_mat5_sizes(bytes, path, max_variable_bytes);
  // A v7.3 (HDF5) variable's data is not checked against the bytes present, and HDF5 fills chunks a
  // file never stored: no variable may claim more than deflate could have packed into the whole file
  // (at most ~1032:1), as check_mat5_sizes bounds a v5 file's compressed variables.
  max_variable_bytes_ = std::min<uint64_t>(max_variable_bytes, 1100 * static_cast<uint64_t>(bytes.size()) + (64 << 10));
  mat_ = Mat_Open(path.c_str(), MAT_ACC_RDONLY);
  require(mat_ != nullptr, path, "not a readable MATLAB .mat file");
}

MatReader::~MatReader() {
  if (mat_) Mat_Close(static_cast<mat_t*>(mat_));
}

std::vector<std::string> MatReader::names() const {
  std::vector<std::string> out;
  auto* mat = static_cast<mat_t*>(mat_);
  Mat_Rewind(mat);
  while (matvar_t* v = Mat_VarReadNextInfo(mat)) {
    if (v->name) out.emplace_back(v->name);
    Mat_VarFree(v);
  }
  Mat_Rewind(mat);
  return out;
}

bool MatReader::has(const std::string& name) const {
  matvar_t* v = Mat_VarReadInfo(static_cast<mat_t*>(mat_), name.c_str());
  if (!v) return false;
  Mat_VarFree(v);
  return true;
}

torch::Tensor MatReader::read(const std::string& name) const {
  // The variable's header first: only a real numeric array is read. A struct, cell or sparse array
  // is refused before matio reads its contents, which check_mat5_sizes does not vouch for (found by
  // scripts/fuzz.sh: a struct whose field claims 520 M doubles made matio allocate 4 GB).
  matvar_t* info = Mat_VarReadInfo(static_cast<mat_t*>(mat_), name.c_str());
  if (!info) {
    std::string present;
    for (const auto& n : names()) present += (present.empty() ? "" : " ") + n;
    // A v7.3 header before a damaged HDF5 body opens, and lists nothing.
    require(!present.empty(), path_,
            "holds no variable that can be read (a damaged file, or an empty one); missing '" + name + "'");
    throw Error(path_, "missing variable '" + name + "' (file has: " + present + ")");
  }
  const bool numeric = info->isComplex == 0 && is_supported_numeric(info->class_type);
  // The size it claims, before matio allocates it (v7.3 files are HDF5's: check_mat5_sizes reads v5 only).
  uint64_t bytes = element_bytes(info->class_type);
  bool overflow = false;
  for (int i = 0; i < info->rank; ++i)
    overflow |= __builtin_mul_overflow(bytes, static_cast<uint64_t>(info->dims[i]), &bytes);
  std::string claimed;
  for (int i = 0; i < info->rank; ++i) claimed += (i ? "x" : "") + std::to_string(info->dims[i]);
  Mat_VarFree(info);
  require(numeric, path_, "variable '" + name + "' is not a real numeric array");
  require(!overflow && bytes <= max_variable_bytes_, path_,
          "variable '" + name + "' claims " + claimed + " values (" + (overflow ? "over 2^64" : std::to_string(bytes)) +
              " bytes), more than the " + std::to_string(max_variable_bytes_) +
              " bytes its reader allows (a damaged or hostile file, or not the file expected here)");
  matvar_t* v = Mat_VarRead(static_cast<mat_t*>(mat_), name.c_str());
  require(v != nullptr, path_, "variable '" + name + "' cannot be read (a damaged file?)");
  std::unique_ptr<matvar_t, void (*)(matvar_t*)> guard(v, Mat_VarFree);
  require(v->isComplex == 0 && is_supported_numeric(v->class_type) && v->data != nullptr, path_,
          "variable '" + name + "' is not a real numeric array");
  std::vector<int64_t> dims(v->dims, v->dims + v->rank);
  int64_t count = 1;
  for (auto d : dims) count *= d;
  // copy=true: the buffer belongs to matio and is freed with the variable.
  auto flat = torch::from_blob(v->data, {count}, torch_type(v->class_type)).to(torch::kFloat64, false, true);
  return from_column_major(flat, dims);
}

torch::Tensor MatReader::read(const std::string& name, const std::vector<int64_t>& expected) const {
  auto t = read(name);
  std::vector<int64_t> shape(t.sizes().begin(), t.sizes().end());
  // MATLAB has no 1-D arrays: accept a 1xN or Nx1 variable where a vector is expected.
  if (expected.size() == 1 && t.dim() == 2 && (shape[0] == 1 || shape[1] == 1)) {
    t = t.reshape({-1});
    shape = {t.size(0)};
  }
  require(shape == expected, path_,
          "variable '" + name + "' is " + shape_string(shape) + ", expected " + shape_string(expected));
  return t;
}

double MatReader::read_scalar(const std::string& name) const {
  auto t = read(name);
  require(t.numel() == 1, path_, "variable '" + name + "' should be a scalar");
  return t.item<double>();
}

void write_mat(const std::filesystem::path& path, const std::map<std::string, torch::Tensor>& vars,
               MatVersion version) {
  write_atomically(path, [&](const std::filesystem::path& tmp) {
    const auto ft = version == MatVersion::v73 ? MAT_FT_MAT73 : MAT_FT_MAT5;
    mat_t* mat = Mat_CreateVer(tmp.c_str(), nullptr, ft);
    require(mat != nullptr, path,
            version == MatVersion::v73 ? "cannot create a v7.3 .mat file (matio built without HDF5?)"
                                       : "cannot create .mat file");
    std::unique_ptr<mat_t, int (*)(mat_t*)> guard(mat, Mat_Close);
    for (const auto& [name, tensor] : vars) {
      auto data = to_column_major(tensor.detach().to(torch::kCPU, torch::kFloat64));
      std::vector<size_t> dims(tensor.sizes().begin(), tensor.sizes().end());
      if (dims.size() == 1) dims.push_back(1);  // MATLAB vectors are Nx1
      if (dims.empty()) dims = {1, 1};
      matvar_t* v = Mat_VarCreate(name.c_str(), MAT_C_DOUBLE, MAT_T_DOUBLE, static_cast<int>(dims.size()), dims.data(),
                                  data.data_ptr<double>(), MAT_F_DONT_COPY_DATA);
      require(v != nullptr, path, "cannot create variable '" + name + "'");
      const int rc = Mat_VarWrite(mat, v, MAT_COMPRESSION_ZLIB);
      Mat_VarFree(v);
      require(rc == 0, path, "writing variable '" + name + "' failed");
    }
  });
}

}  // namespace flatnet
