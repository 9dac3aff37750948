#include "io/mat.hpp"

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

}  // namespace

MatReader::MatReader(const std::filesystem::path& path) : path_(path) {
  check_mat5_sizes(read_file_text(path), path);  // regular file, sizes and counts checked before matio allocates
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
    throw Error(path_, "missing variable '" + name + "' (file has: " + present + ")");
  }
  const bool numeric = info->isComplex == 0 && is_supported_numeric(info->class_type);
  Mat_VarFree(info);
  require(numeric, path_, "variable '" + name + "' is not a real numeric array");
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
