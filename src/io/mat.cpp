#include "io/mat.hpp"

#include <algorithm>
#include <cstring>
#include <functional>
#include <memory>
#include <stdexcept>

#include <H5Epublic.h>
#include <matio.h>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/isolated_reader.hpp"
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

bool is_supported_numeric(matio_classes c) {
  return c == MAT_C_DOUBLE || c == MAT_C_SINGLE || c == MAT_C_INT8 || c == MAT_C_UINT8 || c == MAT_C_INT16 ||
         c == MAT_C_INT32 || c == MAT_C_INT64;
}

// The one table of the numeric classes read: f(T{}) with the class's C++ element type T. Callers
// check is_supported_numeric first.
template <class F>
auto with_element_type(matio_classes c, F&& f) {
  switch (c) {
    case MAT_C_DOUBLE:
      return f(double{});
    case MAT_C_SINGLE:
      return f(float{});
    case MAT_C_INT8:
      return f(int8_t{});
    case MAT_C_UINT8:
      return f(uint8_t{});
    case MAT_C_INT16:
      return f(int16_t{});
    case MAT_C_INT32:
      return f(int32_t{});
    case MAT_C_INT64:
      return f(int64_t{});
    default:
      throw std::invalid_argument("mat: a class that is_supported_numeric refuses");
  }
}

torch::ScalarType torch_type(matio_classes c) {
  return with_element_type(c, [](auto t) { return c10::CppTypeToScalarType<decltype(t)>::value; });
}

uint64_t element_bytes(matio_classes c) {
  return with_element_type(c, [](auto t) { return uint64_t{sizeof t}; });
}

// HDF5 prints its error stack to stderr on a damaged v7.3 file; flatnet names the file itself.
void silence_hdf5_errors() {
  static const bool silenced = H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr) >= 0;
  (void)silenced;
}

// Why a variable whose header `info` shows is not read ("" when it may be): not a real numeric
// array, or more bytes than the reader allows. Checked before matio reads or allocates its data.
std::string refusal(const matvar_t* info, const std::string& name, uint64_t max_bytes) {
  if (info->isComplex != 0 || !is_supported_numeric(info->class_type))
    return "variable '" + name + "' is not a real numeric array";
  uint64_t bytes = element_bytes(info->class_type);
  bool overflow = false;
  std::string claimed;
  for (int i = 0; i < info->rank; ++i) {
    overflow |= __builtin_mul_overflow(bytes, static_cast<uint64_t>(info->dims[i]), &bytes);
    claimed += (i ? "x" : "") + std::to_string(info->dims[i]);
  }
  if (!overflow && bytes <= max_bytes) return "";
  return "variable '" + name + "' claims " + claimed + " values (" + (overflow ? "over 2^64" : std::to_string(bytes)) +
         " bytes), more than the " + std::to_string(max_bytes) +
         " bytes its reader allows (a damaged or hostile file, or not the file expected here)";
}

// A read variable as float64 values in MATLAB's column-major order, without torch (the isolated
// child of a v7.3 read must not start OpenMP threads after fork).
template <class T>
void append_as_doubles(const void* data, uint64_t count, std::string& out) {
  const auto* v = static_cast<const T*>(data);
  for (uint64_t i = 0; i < count; ++i) {
    const double d = static_cast<double>(v[i]);
    out.append(reinterpret_cast<const char*>(&d), sizeof d);
  }
}

void append_values(const matvar_t* v, uint64_t count, std::string& out) {
  with_element_type(v->class_type, [&](auto t) { append_as_doubles<decltype(t)>(v->data, count, out); });
}

template <class T>
void append_pod(std::string& out, T value) {
  out.append(reinterpret_cast<const char*>(&value), sizeof value);
}

void append_text(std::string& out, const std::string& text) {
  append_pod<uint32_t>(out, static_cast<uint32_t>(text.size()));
  out += text;
}

constexpr uint32_t kMaxVariables = 4096;
constexpr uint32_t kMaxRank = 32;

// The isolated child of a v7.3 read: every variable, in the file's order, as
//   name, 0, rank, dims (int64), values (float64, column-major)   or   name, 1, why it is refused.
std::string v73_records(const std::filesystem::path& path, uint64_t max_bytes, const std::function<void()>& lock_down) {
  silence_hdf5_errors();
  mat_t* mat = Mat_Open(path.c_str(), MAT_ACC_RDONLY);
  lock_down();  // the file is open: from here on HDF5 can only read it
  require(mat != nullptr, path, "not a readable MATLAB .mat file");
  std::unique_ptr<mat_t, int (*)(mat_t*)> guard(mat, Mat_Close);
  std::vector<std::string> names;
  while (matvar_t* info = Mat_VarReadNextInfo(mat)) {
    if (info->name && names.size() < kMaxVariables) names.emplace_back(info->name);
    Mat_VarFree(info);
  }
  std::string out;
  for (const auto& name : names) {
    append_text(out, name);
    std::unique_ptr<matvar_t, void (*)(matvar_t*)> info(Mat_VarReadInfo(mat, name.c_str()), Mat_VarFree);
    auto why = info ? refusal(info.get(), name, max_bytes) : "variable '" + name + "' cannot be read (a damaged file?)";
    if (why.empty() && info->rank > static_cast<int>(kMaxRank)) why = "variable '" + name + "' has too many dimensions";
    std::unique_ptr<matvar_t, void (*)(matvar_t*)> v(why.empty() ? Mat_VarRead(mat, name.c_str()) : nullptr,
                                                     Mat_VarFree);
    if (why.empty() &&
        (!v || v->data == nullptr || v->rank != info->rank || !refusal(v.get(), name, max_bytes).empty()))
      why = "variable '" + name + "' cannot be read (a damaged file?)";
    out += static_cast<char>(why.empty() ? 0 : 1);
    if (!why.empty()) {
      append_text(out, why);
      continue;
    }
    uint64_t count = 1;
    append_pod<uint32_t>(out, static_cast<uint32_t>(v->rank));
    for (int i = 0; i < v->rank; ++i) {
      append_pod<int64_t>(out, static_cast<int64_t>(v->dims[i]));
      count *= v->dims[i];  // bounded: refusal() checked the product against max_bytes
    }
    append_values(v.get(), count, out);
  }
  return out;
}

// The parent's reading of those records: the child may have been subverted, so every length is
// checked against the bytes present before anything is allocated.
class RecordCursor {
 public:
  RecordCursor(const std::string& bytes, const std::filesystem::path& path) : bytes_(bytes), path_(path) {}
  bool done() const { return at_ == bytes_.size(); }
  template <class T>
  T pod() {
    T value;
    std::memcpy(&value, take(sizeof value), sizeof value);
    return value;
  }
  std::string text() {
    const auto n = pod<uint32_t>();
    return std::string(take(n), n);
  }
  const char* take(uint64_t n) {
    require(n <= bytes_.size() - at_, path_, "its reader handed back a damaged record");
    const char* p = bytes_.data() + at_;
    at_ += n;
    return p;
  }

 private:
  const std::string& bytes_;
  const std::filesystem::path& path_;
  uint64_t at_ = 0;
};

}  // namespace

struct MatReader::Variables {
  std::vector<std::string> names;  // in the file's order
  std::map<std::string, torch::Tensor> values;
  std::map<std::string, std::string> refused;  // name -> why
};

namespace {

std::unique_ptr<const MatReader::Variables> parse_records(const std::string& bytes, const std::filesystem::path& path) {
  auto out = std::make_unique<MatReader::Variables>();
  RecordCursor c(bytes, path);
  while (!c.done()) {
    require(out->names.size() < kMaxVariables, path, "its reader handed back a damaged record");
    const auto name = c.text();
    out->names.push_back(name);
    if (c.pod<char>() != 0) {
      out->refused[name] = c.text();
      continue;
    }
    const auto rank = c.pod<uint32_t>();
    require(rank <= kMaxRank, path, "its reader handed back a damaged record");
    std::vector<int64_t> dims;
    uint64_t count = 1;
    for (uint32_t i = 0; i < rank; ++i) {
      dims.push_back(c.pod<int64_t>());
      require(dims.back() >= 0 && !__builtin_mul_overflow(count, static_cast<uint64_t>(dims.back()), &count) &&
                  count <= bytes.size() / 8,
              path, "its reader handed back a damaged record");
    }
    const char* values = c.take(count * 8);
    auto flat = torch::empty({static_cast<int64_t>(count)}, torch::kFloat64);
    std::memcpy(flat.data_ptr<double>(), values, count * 8);
    out->values[name] = from_column_major(flat, dims);
  }
  return out;
}

}  // namespace

MatReader::MatReader(const std::filesystem::path& path, uint64_t max_variable_bytes)
    : path_(path), max_variable_bytes_(max_variable_bytes) {
  // Regular file, sizes and counts checked before matio allocates.
  const auto bytes = read_file_text(path);
  check_mat5_sizes(bytes, path, max_variable_bytes);
  const bool v73 = bytes.size() >= 128 && (static_cast<unsigned char>(bytes[124]) | bytes[125] << 8) == 0x0200;
  if (!v73) {
    mat_ = Mat_Open(path.c_str(), MAT_ACC_RDONLY);
    require(mat_ != nullptr, path, "not a readable MATLAB .mat file");
    return;
  }
  // A v7.3 (HDF5) variable's data is not checked against the bytes present, and HDF5 fills chunks a
  // file never stored: no variable may claim more than deflate could have packed into the whole file
  // (at most ~1032:1), as check_mat5_sizes bounds a v5 file's compressed variables.
  max_variable_bytes_ = std::min<uint64_t>(max_variable_bytes, 1100 * static_cast<uint64_t>(bytes.size()) + (64 << 10));
  IsolatedReadOptions limits;
  // float64 values of at most kMaxVariables variables, each within the bound (an int8 one grows 8x).
  limits.max_output_bytes = std::min<uint64_t>(8 * max_variable_bytes_, 16ull << 30) + (1 << 20);
  limits.max_memory_bytes = 3 * limits.max_output_bytes + (1ull << 30);
  limits.reader = "its HDF5 (MATLAB v7.3) reader";
  const auto records = read_isolated(
      path, [&](const std::function<void()>& lock_down) { return v73_records(path, max_variable_bytes_, lock_down); },
      limits);
  v73_ = parse_records(records, path);
}

MatReader::~MatReader() {
  if (mat_) Mat_Close(static_cast<mat_t*>(mat_));
}

std::vector<std::string> MatReader::names() const {
  if (v73_) return v73_->names;
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
  if (v73_) return v73_->values.count(name) + v73_->refused.count(name) > 0;
  matvar_t* v = Mat_VarReadInfo(static_cast<mat_t*>(mat_), name.c_str());
  if (!v) return false;
  Mat_VarFree(v);
  return true;
}

void MatReader::missing(const std::string& name) const {
  std::string present;
  for (const auto& n : names()) present += (present.empty() ? "" : " ") + n;
  // A v7.3 header before a damaged HDF5 body opens, and lists nothing.
  require(!present.empty(), path_,
          "holds no variable that can be read (a damaged file, or an empty one); missing '" + name + "'");
  throw Error(path_, "missing variable '" + name + "' (file has: " + present + ")");
}

torch::Tensor MatReader::read(const std::string& name) const {
  if (v73_) {
    if (const auto r = v73_->refused.find(name); r != v73_->refused.end()) throw Error(path_, r->second);
    const auto v = v73_->values.find(name);
    if (v == v73_->values.end()) missing(name);
    return v->second.clone();
  }
  // The variable's header first: only a real numeric array is read. A struct, cell or sparse array
  // is refused before matio reads its contents, which check_mat5_sizes does not vouch for (found by
  // scripts/fuzz.sh: a struct whose field claims 520 M doubles made matio allocate 4 GB).
  std::unique_ptr<matvar_t, void (*)(matvar_t*)> info(Mat_VarReadInfo(static_cast<mat_t*>(mat_), name.c_str()),
                                                      Mat_VarFree);
  if (!info) missing(name);
  const auto why = refusal(info.get(), name, max_variable_bytes_);
  require(why.empty(), path_, why);
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
