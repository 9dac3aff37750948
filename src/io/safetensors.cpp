#include "io/safetensors.hpp"

#include <nlohmann/json.hpp>
#include <zlib.h>

#include <algorithm>
#include <cstring>
#include <set>

#include "core/error.hpp"
#include "core/util.hpp"

static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__, "safetensors stores little-endian elements");

namespace flatnet {
namespace {

using json = nlohmann::json;

struct DtypeName {
  const char* name;
  c10::ScalarType type;
};
constexpr DtypeName kDtypes[] = {{"F64", torch::kFloat64}, {"F32", torch::kFloat32}, {"BF16", torch::kBFloat16},
                                 {"F16", torch::kFloat16}, {"I64", torch::kInt64},   {"I32", torch::kInt32},
                                 {"I16", torch::kInt16},   {"I8", torch::kInt8},     {"U8", torch::kUInt8},
                                 {"BOOL", torch::kBool}};

const char* dtype_name(c10::ScalarType t) {
  for (const auto& d : kDtypes)
    if (d.type == t) return d.name;
  throw Error("safetensors writer: no safetensors dtype for " + std::string(c10::toString(t)));
}

c10::ScalarType dtype_of(const std::string& name, const std::filesystem::path& path, const std::string& tensor) {
  for (const auto& d : kDtypes)
    if (name == d.name) return d.type;
  throw Error(path, "tensor '" + tensor + "' has dtype '" + name + "', which flatnet does not read (" +
                        "F64, F32, BF16, F16, I64, I32, I16, I8, U8, BOOL)");
}

// zlib's CRC-32 (Python: zlib.crc32) of the byte buffer, as 8 hex digits: safetensors itself has
// no checksum, and a flipped bit in a weight would otherwise load as a wrong model.
std::string buffer_crc32(const char* data, uint64_t size) {
  uLong c = crc32(0, nullptr, 0);
  for (uint64_t at = 0; at < size;) {
    const auto n = static_cast<uInt>(std::min<uint64_t>(size - at, 1u << 30));
    c = crc32(c, reinterpret_cast<const Bytef*>(data + at), n);
    at += n;
  }
  char hex[9];
  std::snprintf(hex, sizeof hex, "%08lx", static_cast<unsigned long>(c) & 0xffffffffUL);
  return hex;
}

uint64_t little_endian_u64(const char* p) {
  uint64_t v = 0;
  for (int i = 7; i >= 0; --i) v = (v << 8) | static_cast<unsigned char>(p[i]);
  return v;
}

// Parses the header, refusing nesting deeper than a tensor's shape list and any name given twice
// within one object (JSON allows both; a reader that took the last of two names would disagree
// with one that took the first).
// Keys are counted while parsing, so a header of millions of tiny keys is refused before its
// document is built (nlohmann's objects cost ~100 bytes a key).
json parse_header(const std::string& text, const std::filesystem::path& path, int64_t max_keys) {
  std::vector<std::set<std::string>> keys;
  int64_t key_count = 0;
  auto check = [&](int depth, json::parse_event_t event, json& parsed) {
    if (depth > 3) throw Error(path, "safetensors header nests deeper than a tensor's shape (hostile file?)");
    if (event == json::parse_event_t::key && ++key_count > max_keys)
      throw Error(path, "safetensors header holds more than " + std::to_string(max_keys) +
                            " keys (tensors and metadata), over the limit");
    if (event == json::parse_event_t::object_start) keys.emplace_back();
    if (event == json::parse_event_t::object_end && !keys.empty()) keys.pop_back();
    if (event == json::parse_event_t::key && !keys.empty() && !keys.back().insert(parsed.get<std::string>()).second)
      throw Error(path, "safetensors header names '" + parsed.get<std::string>() + "' twice");
    return true;
  };
  try {
    return json::parse(text, check);
  } catch (const json::exception& e) {
    throw Error(path, "safetensors header is not valid JSON (" + std::string(e.what()).substr(0, 160) + ")");
  }
}

struct Entry {
  std::string name;
  c10::ScalarType type;
  std::vector<int64_t> shape;
  uint64_t begin = 0, end = 0;
};

uint64_t checked_u64(const json& v, const std::filesystem::path& path, const std::string& what) {
  if (!v.is_number_unsigned() && !(v.is_number_integer() && v.get<int64_t>() >= 0))
    throw Error(path, what + " is not a non-negative integer");
  return v.get<uint64_t>();
}

Entry parse_entry(const std::string& name, const json& v, const std::filesystem::path& path) {
  const auto where = "tensor '" + name + "'";
  if (name.empty()) throw Error(path, "a tensor has an empty name");
  if (!v.is_object()) throw Error(path, where + " is not described by an object");
  for (const char* key : {"dtype", "shape", "data_offsets"})
    if (!v.contains(key)) throw Error(path, where + " lacks '" + key + "'");
  if (!v["dtype"].is_string()) throw Error(path, where + ": dtype is not a string");
  if (!v["shape"].is_array()) throw Error(path, where + ": shape is not a list");
  const auto& offsets = v["data_offsets"];
  if (!offsets.is_array() || offsets.size() != 2) throw Error(path, where + ": data_offsets is not [BEGIN, END]");
  Entry e;
  e.name = name;
  e.type = dtype_of(v["dtype"].get<std::string>(), path, name);
  if (v["shape"].size() > 16) throw Error(path, where + " has " + std::to_string(v["shape"].size()) + " dimensions");
  uint64_t bytes = c10::elementSize(e.type);
  for (const auto& s : v["shape"]) {
    const auto n = checked_u64(s, path, where + ": a shape entry");
    if (n > static_cast<uint64_t>(INT64_MAX) || (n != 0 && bytes > UINT64_MAX / n))
      throw Error(path, where + ": its shape overflows 64 bits (hostile file?)");
    bytes *= n;
    e.shape.push_back(static_cast<int64_t>(n));
  }
  e.begin = checked_u64(offsets[0], path, where + ": data_offsets[0]");
  e.end = checked_u64(offsets[1], path, where + ": data_offsets[1]");
  if (e.end < e.begin || e.end - e.begin != bytes)
    throw Error(path, where + " spans " + std::to_string(e.end - e.begin) + " bytes, its dtype and shape need " +
                          std::to_string(bytes));
  return e;
}

torch::Tensor tensor_from(const Entry& e, const char* data, const std::filesystem::path& path) {
  auto t = torch::empty(e.shape, torch::TensorOptions().dtype(e.type));
  if (e.end > e.begin) std::memcpy(t.data_ptr(), data + e.begin, e.end - e.begin);
  if (e.type == torch::kBool) {  // any byte but 0 and 1 is not a bool (undefined in C++)
    const auto* p = reinterpret_cast<const unsigned char*>(data + e.begin);
    if (std::any_of(p, p + (e.end - e.begin), [](unsigned char c) { return c > 1; }))
      throw Error(path, "tensor '" + e.name + "' (BOOL) holds bytes other than 0 and 1");
  }
  return t;
}

}  // namespace

const torch::Tensor* SafeTensors::find(const std::string& name) const {
  for (const auto& [n, t] : tensors)
    if (n == name) return &t;
  return nullptr;
}

const std::string& SafeTensors::meta(const std::string& key, const std::filesystem::path& where) const {
  const auto it = metadata.find(key);
  if (it == metadata.end()) throw Error(where, "has no '" + key + "' in its metadata (not a flatnet file?)");
  return it->second;
}

bool looks_like_safetensors(const std::string& bytes) {
  if (bytes.size() < 10) return false;
  const auto n = little_endian_u64(bytes.data());
  return n >= 2 && n <= bytes.size() - 8 && bytes[8] == '{';
}

std::string safetensors_bytes(const std::vector<std::pair<std::string, torch::Tensor>>& tensors,
                              const std::map<std::string, std::string>& metadata) {
  json header = json::object();
  std::vector<torch::Tensor> data;
  uint64_t offset = 0;
  std::set<std::string> names;
  for (const auto& [name, t] : tensors) {
    if (name.empty() || name == "__metadata__" || !names.insert(name).second)
      throw Error("safetensors writer: tensor name '" + name + "' is empty, reserved or given twice");
    auto c = t.detach().to(torch::kCPU).contiguous();
    const uint64_t n = c.nbytes();
    header[name] = {
        {"dtype", dtype_name(c.scalar_type())}, {"shape", c.sizes().vec()}, {"data_offsets", {offset, offset + n}}};
    offset += n;
    data.push_back(c);
  }
  std::string buffer;
  buffer.reserve(offset);
  for (const auto& c : data) buffer.append(static_cast<const char*>(c.data_ptr()), c.nbytes());
  auto meta = metadata;
  meta[kCrcKey] = buffer_crc32(buffer.data(), buffer.size());
  header["__metadata__"] = meta;
  std::string text = header.dump();
  text.append((8 - (8 + text.size()) % 8) % 8, ' ');  // the buffer starts 8-byte aligned
  std::string out(8, '\0');
  for (int i = 0; i < 8; ++i) out[i] = static_cast<char>((static_cast<uint64_t>(text.size()) >> (8 * i)) & 0xff);
  out.reserve(8 + text.size() + offset);
  out += text;
  out += buffer;
  return out;
}

void write_safetensors(const std::filesystem::path& path,
                       const std::vector<std::pair<std::string, torch::Tensor>>& tensors,
                       const std::map<std::string, std::string>& metadata) {
  write_bytes_atomically(path, safetensors_bytes(tensors, metadata));
}

namespace {

// The header's length N from the file's first 8 bytes, checked against the limit and against the
// `available` bytes that follow them (the whole file's, or a header-only read's).
uint64_t header_length(const std::string& bytes, uint64_t available, const std::filesystem::path& path,
                       const SafeTensorsLimits& limits) {
  if (bytes.size() < 8) throw Error(path, "is not a safetensors file (" + std::to_string(bytes.size()) + " bytes)");
  const uint64_t n = little_endian_u64(bytes.data());
  if (n > limits.max_header_bytes)
    throw Error(path, "safetensors header claims " + std::to_string(n) + " bytes, over the limit of " +
                          std::to_string(limits.max_header_bytes));
  if (n > available)
    throw Error(path, "truncated: the safetensors header claims " + std::to_string(n) + " bytes, the file holds " +
                          std::to_string(available));
  return n;
}

// The header object from bytes [8, 8 + n), its size within the limits.
json header_object(const std::string& bytes, uint64_t n, const std::filesystem::path& path,
                   const SafeTensorsLimits& limits) {
  if (n < 2 || bytes.size() < 9 || bytes[8] != '{')
    throw Error(path, "is not a safetensors file (its header is not a JSON object)");
  // Each tensor's entry has 4 keys (its name, dtype, shape, data_offsets); metadata up to its own limit.
  auto header = parse_header(bytes.substr(8, n), path, 4 * (limits.max_tensors + 1) + limits.max_metadata_keys);
  if (!header.is_object()) throw Error(path, "safetensors header is not a JSON object");
  if (static_cast<int64_t>(header.size()) > limits.max_tensors + 1)
    throw Error(path, "safetensors header lists " + std::to_string(header.size()) + " tensors, over the limit");
  return header;
}

// "__metadata__" as strings (empty when the header has none).
std::map<std::string, std::string> metadata_of(const json& header, const std::filesystem::path& path,
                                               const SafeTensorsLimits& limits) {
  std::map<std::string, std::string> out;
  const auto it = header.find("__metadata__");
  if (it == header.end()) return out;
  const auto& v = *it;
  if (!v.is_object()) throw Error(path, "__metadata__ is not an object");
  if (static_cast<int64_t>(v.size()) > limits.max_metadata_keys)
    throw Error(path, "__metadata__ holds " + std::to_string(v.size()) + " keys, over the limit of " +
                          std::to_string(limits.max_metadata_keys));
  for (const auto& [k, s] : v.items()) {
    if (!s.is_string()) throw Error(path, "__metadata__ '" + k + "' is not a string");
    out[k] = s.get<std::string>();
  }
  return out;
}

}  // namespace

SafeTensors parse_safetensors(const std::string& bytes, const std::filesystem::path& path,
                              const SafeTensorsLimits& limits) {
  const uint64_t n = header_length(bytes, bytes.size() >= 8 ? bytes.size() - 8 : 0, path, limits);
  const auto header = header_object(bytes, n, path, limits);
  SafeTensors out;
  out.metadata = metadata_of(header, path, limits);
  std::vector<Entry> entries;
  for (const auto& [name, v] : header.items())
    if (name != "__metadata__") entries.push_back(parse_entry(name, v, path));
  // The entries must tile the buffer exactly: no holes, no overlaps, nothing past the end.
  std::sort(entries.begin(), entries.end(),
            [](const Entry& a, const Entry& b) { return a.begin != b.begin ? a.begin < b.begin : a.end < b.end; });
  const uint64_t buffer = bytes.size() - 8 - n;
  uint64_t at = 0;
  for (const auto& e : entries) {
    if (e.begin != at)
      throw Error(path, "tensor '" + e.name + "' starts at byte " + std::to_string(e.begin) +
                            " of the buffer, expected " + std::to_string(at) + " (holes or overlapping tensors)");
    if (e.end > buffer)
      throw Error(path, "truncated: tensor '" + e.name + "' ends at byte " + std::to_string(e.end) + " of a " +
                            std::to_string(buffer) + "-byte buffer");
    at = e.end;
  }
  if (at != buffer)
    throw Error(path, std::to_string(buffer - at) + " bytes after the last tensor belong to none (damaged file?)");
  const char* data = bytes.data() + 8 + n;
  if (const auto crc = out.metadata.find(kCrcKey); crc != out.metadata.end()) {
    if (crc->second != buffer_crc32(data, buffer))
      throw Error(
          path, "damaged file: its tensors fail the CRC-32 the file records (the bytes changed after it was written)");
    out.metadata.erase(crc);
  }
  for (const auto& e : entries) out.tensors.emplace_back(e.name, tensor_from(e, data, path));
  return out;
}

SafeTensors read_safetensors(const std::filesystem::path& path, const SafeTensorsLimits& limits) {
  return parse_safetensors(read_file_text(path, limits.max_file_bytes), path, limits);
}

std::map<std::string, std::string> read_safetensors_metadata(const std::filesystem::path& path,
                                                             const SafeTensorsLimits& limits) {
  const auto first = read_file_head(path, 8);
  const uint64_t claimed = header_length(first, limits.max_header_bytes, path, limits);
  const auto head = read_file_head(path, 8 + claimed);  // {8 + N bytes}, or fewer in a truncated file
  const uint64_t n = header_length(head, head.size() - 8, path, limits);
  auto metadata = metadata_of(header_object(head, n, path, limits), path, limits);
  metadata.erase(kCrcKey);  // the buffer it covers is not read here
  return metadata;
}

}  // namespace flatnet
