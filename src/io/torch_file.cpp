#include "io/torch_file.hpp"

#include <zlib.h>

#include <caffe2/serialize/inline_container.h>

#include <cstring>
#include <functional>
#include <map>
#include <sstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/pickle.hpp"

namespace flatnet {
namespace {

using namespace pickle;  // the pickle machine (io/pickle.hpp)

// A persistent id ('storage', storage_type, key, location, numel[, view_metadata]) -> a storage
// value whose tensor is filled by the container.
PyRef storage_from_id(const PyRef& pid, std::map<std::string, std::shared_ptr<Storage>>& storages,
                      const std::filesystem::path& file) {
  if (pid->kind != Kind::tuple || pid->items.size() < 5 || pid->items[0]->text != "storage" ||
      pid->items[1]->kind != Kind::global || pid->items[2]->kind != Kind::string)
    throw Error(file, "malformed persistent id (expected ('storage', type, key, location, size))");
  const auto type = storage_types().find(pid->items[1]->text);
  if (type == storage_types().end()) throw Error(file, "unknown storage type '" + pid->items[1]->text + "'");
  if (pid->items.size() > 5 && pid->items[5]->kind != Kind::none)
    throw Error(file, "uses storage views (view_metadata), a format of PyTorch before 0.4 that flatnet does not read");
  auto& s = storages[pid->items[2]->text];
  if (!s) {
    s = std::make_shared<Storage>();
    s->dtype = type->second;
    s->numel = as_int(pid->items[4], "storage size", file);
    if (s->numel < 0 || static_cast<uint64_t>(s->numel) > kMaxInputBytes / c10::elementSize(s->dtype))
      throw Error(file, "storage '" + pid->items[2]->text + "' claims " + std::to_string(s->numel) + " elements");
  }
  auto v = make_text(Kind::storage, pid->items[2]->text);
  return v;
}

torch::Tensor elements(const char* data, size_t bytes, c10::ScalarType dtype, int64_t numel,
                       const std::filesystem::path& file, const std::string& key) {
  if (numel < 0 || static_cast<uint64_t>(numel) > bytes / c10::elementSize(dtype))
    throw Error(file, "storage '" + key + "' is truncated: " + std::to_string(bytes) + " bytes for " +
                          std::to_string(numel) + " elements");
  const auto need = static_cast<size_t>(numel) * c10::elementSize(dtype);
  if (bytes < need)
    throw Error(file, "storage '" + key + "' is truncated: " + std::to_string(bytes) + " of " + std::to_string(need) +
                          " bytes");
  auto t = torch::empty({numel}, torch::TensorOptions().dtype(dtype));
  std::memcpy(t.data_ptr(), data, need);
  return t;
}

// Replaces every storage reference in the tree by its elements and every tensor by its view.
void materialise(PyValue& v, const std::map<std::string, std::shared_ptr<Storage>>& storages,
                 const std::filesystem::path& file) {
  if (v.kind == Kind::tensor && !v.tensor.defined()) {
    const auto& s = storages.at(v.items[0]->text);
    if (!s->data.defined()) throw Error(file, "storage '" + v.items[0]->text + "' has no data in the file");
    std::vector<int64_t> size, stride;
    for (const auto& i : v.items[1]->items) size.push_back(i->integer);
    for (const auto& i : v.items[2]->items) stride.push_back(i->integer);
    // The highest element the view touches must lie in the storage, and the view may not hold more
    // elements than the storage (a 1-element storage viewed as 32768x16384 with stride 0 would
    // make a 2 GB copy out of 4 bytes). Every product is overflow-checked.
    int64_t last = v.integer, numel = 1;
    bool empty = false, overflow = false;
    for (size_t d = 0; d < size.size(); ++d) {
      if (size[d] < 0 || stride[d] < 0) throw Error(file, "malformed tensor: negative size or stride");
      if (size[d] == 0) empty = true;
      int64_t reach = 0;
      overflow |= __builtin_mul_overflow(size[d] > 0 ? size[d] - 1 : 0, stride[d], &reach);
      overflow |= __builtin_add_overflow(last, reach, &last);
      overflow |= __builtin_mul_overflow(numel, size[d], &numel);
    }
    if (overflow) throw Error(file, "malformed tensor: its size or stride overflows 64 bits (hostile file?)");
    if (!empty && (v.integer < 0 || last >= s->numel))
      throw Error(file, "a tensor reaches past the end of storage '" + v.items[0]->text + "'");
    if (!empty && numel > s->numel)
      throw Error(file, "a tensor views its " + std::to_string(s->numel) + "-element storage '" + v.items[0]->text +
                            "' as " + std::to_string(numel) + " elements (overlapping strides; hostile file?)");
    auto t = empty ? torch::empty(size, s->data.options()) : s->data.as_strided(size, stride, v.integer).clone();
    if (t.is_floating_point()) t = t.to(torch::kFloat32);
    v.tensor = t;
    v.items.clear();
    return;
  }
  for (auto& i : v.items) materialise(*i, storages, file);
  for (auto& e : v.entries) {
    materialise(*e.first, storages, file);
    materialise(*e.second, storages, file);
  }
}

PyRef read_zip(const std::filesystem::path& path, bool objects) {
  verify_zip_crcs(path);
  std::unique_ptr<caffe2::serialize::PyTorchStreamReader> reader;
  std::string pickle;
  try {
    reader = std::make_unique<caffe2::serialize::PyTorchStreamReader>(path.string());
    if (!reader->hasRecord("data.pkl")) throw Error(path, "is a zip file but not a torch.save archive (no data.pkl)");
    auto [data, size] = reader->getRecord("data.pkl");
    pickle.assign(static_cast<const char*>(data.get()), size);
  } catch (const c10::Error& e) {
    throw Error(path, "damaged zip container (" + std::string(e.what_without_backtrace()).substr(0, 120) + ")");
  }
  std::map<std::string, std::shared_ptr<Storage>> storages;
  Unpickler u(pickle, 0, path, [&](const PyRef& pid) { return storage_from_id(pid, storages, path); });
  u.objects_ = objects;
  auto root = u.run();
  for (auto& [key, s] : storages) {
    const auto record = "data/" + key;
    try {
      if (!reader->hasRecord(record)) throw Error(path, "storage record '" + record + "' is missing");
      auto [data, size] = reader->getRecord(record);
      s->data = elements(static_cast<const char*>(data.get()), size, s->dtype, s->numel, path, key);
    } catch (const c10::Error& e) {
      throw Error(path, "storage '" + key + "' cannot be read (" +
                            std::string(e.what_without_backtrace()).substr(0, 120) + ")");
    }
  }
  materialise(*root, storages, path);
  return root;
}

PyRef read_legacy(const std::filesystem::path& path, const std::string& bytes) {
  std::map<std::string, std::shared_ptr<Storage>> storages;
  auto no_ids = [&](const PyRef&) -> PyRef { throw Error(path, "malformed legacy header"); };
  size_t pos = 0;
  auto next = [&](std::function<PyRef(const PyRef&)> persistent) {
    Unpickler u(bytes, pos, path, std::move(persistent));
    auto v = u.run();
    pos = u.position();
    return v;
  };
  const auto magic = next(no_ids);
  if (magic->kind != Kind::integer || magic->text != "1950a86a20f9469cfc6c")
    throw Error(path, "not a torch.save file (no legacy magic number and not a zip archive)");
  const auto protocol = next(no_ids);
  if (protocol->kind != Kind::integer || protocol->integer != 1001)
    throw Error(path, "legacy torch.save protocol " + std::to_string(protocol->integer) + ", flatnet reads 1001");
  const auto sys_info = next(no_ids);
  if (auto le = sys_info->get("little_endian"); le && le->kind == Kind::boolean && !le->boolean)
    throw Error(path, "was written on a big-endian machine; flatnet reads little-endian files");
  auto root = next([&](const PyRef& pid) { return storage_from_id(pid, storages, path); });
  const auto keys = next(no_ids);
  if (keys->kind != Kind::list) throw Error(path, "malformed legacy file: no storage key list");
  for (const auto& k : keys->items) {
    if (k->kind != Kind::string) throw Error(path, "malformed legacy file: a storage key is not a string");
    if (pos + 8 > bytes.size()) throw Error(path, "truncated: storage '" + k->text + "' is missing");
    int64_t numel = 0;
    std::memcpy(&numel, bytes.data() + pos, 8);
    pos += 8;
    const auto it = storages.find(k->text);
    if (it == storages.end()) throw Error(path, "malformed legacy file: storage '" + k->text + "' is never used");
    auto& s = *it->second;
    if (numel != s.numel)
      throw Error(path, "storage '" + k->text + "' holds " + std::to_string(numel) + " elements, the pickle says " +
                            std::to_string(s.numel));
    const auto n = static_cast<size_t>(numel) * c10::elementSize(s.dtype);
    s.data = elements(bytes.data() + pos, bytes.size() - pos, s.dtype, numel, path, k->text);
    pos += n;
  }
  materialise(*root, storages, path);
  return root;
}

void collect_tensors(const PyValue& v, const std::string& prefix,
                     std::vector<std::pair<std::string, torch::Tensor>>& out) {
  for (const auto& [k, val] : v.entries) {
    const std::string key = k->kind == Kind::string    ? k->text
                            : k->kind == Kind::integer ? std::to_string(k->integer)
                                                       : "?";
    const auto name = prefix.empty() ? key : prefix + "." + key;
    if (val->kind == Kind::tensor)
      out.emplace_back(name, val->tensor);
    else if (val->kind == Kind::dict)
      collect_tensors(*val, name, out);
  }
}

// A pickle (protocol 2) as Python's torch.save writes it for an OrderedDict of tensors.
class StateDictPickler {
 public:
  std::string bytes;
  void op(unsigned char c) { bytes.push_back(static_cast<char>(c)); }
  void u32(uint32_t v) {
    for (int i = 0; i < 4; ++i) bytes.push_back(static_cast<char>((v >> (8 * i)) & 0xff));
  }
  void global(const std::string& module, const std::string& name) {
    op('c');
    bytes += module + "\n" + name + "\n";
  }
  void string(const std::string& s) {
    op('X');
    u32(static_cast<uint32_t>(s.size()));
    bytes += s;
  }
  void integer(int64_t v) {
    if (v >= 0 && v < 256) {
      op('K');
      op(static_cast<unsigned char>(v));
    } else if (v >= INT32_MIN && v <= INT32_MAX) {
      op('J');
      u32(static_cast<uint32_t>(static_cast<int32_t>(v)));
    } else {
      op(0x8a);
      op(8);
      for (int i = 0; i < 8; ++i) bytes.push_back(static_cast<char>((static_cast<uint64_t>(v) >> (8 * i)) & 0xff));
    }
  }
  void int_tuple(c10::IntArrayRef values) {
    op('(');
    for (auto v : values) integer(v);
    op('t');
  }
  void empty_ordered_dict() {
    global("collections", "OrderedDict");
    op(')');
    op('R');
  }
  // torch._utils._rebuild_tensor_v2(('storage', torch.FloatStorage, key, 'cpu', numel), 0, size, stride, False,
  // OrderedDict())
  void tensor(const torch::Tensor& t, const std::string& storage_key, const std::string& storage_type) {
    global("torch._utils", "_rebuild_tensor_v2");
    op('(');
    op('(');
    string("storage");
    global("torch", storage_type);
    string(storage_key);
    string("cpu");
    integer(t.numel());
    op('t');
    op('Q');  // BINPERSID
    integer(0);
    int_tuple(t.sizes());
    int_tuple(t.strides());
    op(0x89);  // requires_grad False
    empty_ordered_dict();
    op('t');
    op('R');
  }
};

std::string storage_type_name(c10::ScalarType t) {
  for (const auto& [name, type] : storage_types())
    if (type == t) return name.substr(6);  // "torch.FloatStorage" -> "FloatStorage"
  throw Error("torch.save writer: no storage type for " + std::string(c10::toString(t)));
}

}  // namespace

void save_torch_state_dict(const std::filesystem::path& path,
                           const std::vector<std::pair<std::string, torch::Tensor>>& tensors,
                           const std::string& wrap_key) {
  StateDictPickler p;
  std::vector<torch::Tensor> storages;
  p.op(0x80);
  p.op(2);
  if (!wrap_key.empty()) {
    p.op('}');
    p.string(wrap_key);
  }
  p.empty_ordered_dict();
  p.op('(');
  for (const auto& [name, t] : tensors) {
    const auto c = t.detach().contiguous().cpu();
    p.string(name);
    p.tensor(c, std::to_string(storages.size()), storage_type_name(c.scalar_type()));
    storages.push_back(c);
  }
  p.op('u');  // SETITEMS
  if (!wrap_key.empty()) p.op('s');
  p.op('.');
  std::string zip;
  {
    caffe2::serialize::PyTorchStreamWriter writer([&](const void* data, size_t n) {
      zip.append(static_cast<const char*>(data), n);
      return n;
    });
    writer.writeRecord("data.pkl", p.bytes.data(), p.bytes.size());
    for (size_t i = 0; i < storages.size(); ++i)
      writer.writeRecord("data/" + std::to_string(i), storages[i].data_ptr(), storages[i].nbytes());
    writer.writeEndOfFile();
  }
  write_bytes_atomically(path, zip);
}

PyRef PyValue::get(const std::string& key) const {
  for (const auto& [k, v] : entries)
    if (k->kind == Kind::string && k->text == key) return v;
  return nullptr;
}

std::string PyValue::describe() const {
  switch (kind) {
    case Kind::none:
      return "None";
    case Kind::boolean:
      return "bool";
    case Kind::integer:
      return "int";
    case Kind::real:
      return "float";
    case Kind::string:
      return "str";
    case Kind::bytes:
      return "bytes";
    case Kind::list:
      return "list";
    case Kind::tuple:
      return "tuple";
    case Kind::dict:
      return "dict";
    case Kind::storage:
      return "storage";
    case Kind::global:
      return "global " + text;
    case Kind::tensor: {
      std::ostringstream os;
      os << "tensor " << (tensor.defined() ? tensor.sizes() : c10::IntArrayRef{});
      return os.str();
    }
  }
  return "?";
}

PyRef read_torch_file(const std::filesystem::path& path) {
  const auto raw = read_bytes(path, kMaxModelFileBytes);
  const std::string bytes(raw.begin(), raw.end());
  if (bytes.size() >= 4 && bytes.compare(0, 4, "PK\x03\x04") == 0) return read_zip(path, false);
  if (bytes.size() >= 2 && static_cast<unsigned char>(bytes[0]) == 0x80) return read_legacy(path, bytes);
  throw Error(path, bytes.empty() ? "is empty" : "not a torch.save file (neither a zip archive nor a legacy pickle)");
}

PyRef read_torchscript_archive(const std::filesystem::path& path) {
  require(verify_zip_crcs(path), path, "is not a TorchScript archive (not a zip file)");
  return read_zip(path, true);
}

std::vector<std::pair<std::string, torch::Tensor>> tensors_in(const PyValue& dict) {
  std::vector<std::pair<std::string, torch::Tensor>> out;
  collect_tensors(dict, "", out);
  return out;
}

namespace {

uint64_t little_endian(const unsigned char* p, int bytes) {
  uint64_t v = 0;
  for (int i = bytes - 1; i >= 0; --i) v = (v << 8) | p[i];
  return v;
}

}  // namespace

bool verify_zip_crcs(const std::filesystem::path& path) {
  require_regular_file(path);
  std::ifstream in(path, std::ios::binary);
  require(static_cast<bool>(in), path, "cannot read file");
  in.seekg(0, std::ios::end);
  const uint64_t size = static_cast<uint64_t>(in.tellg());
  auto read_at = [&](uint64_t offset, size_t n) {
    std::vector<unsigned char> buf(n);
    if (offset + n > size) throw Error(path, "truncated zip archive (a record lies past the end of the file)");
    in.seekg(static_cast<std::streamoff>(offset));
    in.read(reinterpret_cast<char*>(buf.data()), static_cast<std::streamsize>(n));
    if (!in) throw Error(path, "cannot read the zip archive");
    return buf;
  };
  // End of central directory: the last "PK\5\6" within the final 64 KiB (+ its 22 bytes).
  const uint64_t tail_size = std::min<uint64_t>(size, 65536 + 22);
  if (size < 22) return false;
  const auto tail = read_at(size - tail_size, tail_size);
  int64_t eocd = -1;
  for (int64_t i = static_cast<int64_t>(tail_size) - 22; i >= 0; --i)
    if (little_endian(&tail[i], 4) == 0x06054b50) {
      eocd = i;
      break;
    }
  if (eocd < 0) {
    const auto head = read_at(0, 4);
    if (little_endian(head.data(), 4) == 0x04034b50)
      throw Error(path, "truncated zip archive (no central directory at its end)");
    return false;
  }
  uint64_t entries = little_endian(&tail[eocd + 10], 2), cd_offset = little_endian(&tail[eocd + 16], 4);
  if ((entries == 0xFFFF || cd_offset == 0xFFFFFFFF) && eocd >= 20 &&
      little_endian(&tail[eocd - 20], 4) == 0x07064b50) {  // zip64: locator -> zip64 end record
    const auto record = read_at(little_endian(&tail[eocd - 20 + 8], 8), 56);
    entries = little_endian(&record[32], 8);
    cd_offset = little_endian(&record[48], 8);
  }
  uint64_t at = cd_offset;
  std::vector<char> chunk(1 << 20);
  for (uint64_t e = 0; e < entries; ++e) {
    const auto header = read_at(at, 46);
    if (little_endian(header.data(), 4) != 0x02014b50) throw Error(path, "damaged zip archive (central directory)");
    const auto method = little_endian(&header[10], 2);
    const auto crc = static_cast<uint32_t>(little_endian(&header[16], 4));
    uint64_t compressed = little_endian(&header[20], 4), local = little_endian(&header[42], 4);
    const auto name_len = little_endian(&header[28], 2), extra_len = little_endian(&header[30], 2),
               comment_len = little_endian(&header[32], 2);
    const auto name_extra = read_at(at + 46, name_len + extra_len);
    const std::string name(name_extra.begin(), name_extra.begin() + static_cast<std::ptrdiff_t>(name_len));
    // zip64 extra field: the 8-byte values of the fields saturated above, in this order.
    const uint64_t uncompressed32 = little_endian(&header[24], 4);
    for (size_t x = name_len; x + 4 <= name_extra.size();) {
      const auto id = little_endian(&name_extra[x], 2), len = little_endian(&name_extra[x + 2], 2);
      if (id == 0x0001) {
        size_t f = x + 4;
        if (uncompressed32 == 0xFFFFFFFF && f + 8 <= x + 4 + len) f += 8;
        if (compressed == 0xFFFFFFFF && f + 8 <= x + 4 + len) compressed = little_endian(&name_extra[f], 8), f += 8;
        if (local == 0xFFFFFFFF && f + 8 <= x + 4 + len) local = little_endian(&name_extra[f], 8);
      }
      x += 4 + len;
    }
    at += 46 + name_len + extra_len + comment_len;
    // torch.save and TorchScript archives store the pickle and the tensors uncompressed; such an
    // entry compressed would be inflated to whatever size it claims (a zip bomb), so it is refused.
    // Other entries (a TorchScript archive's code/, which flatnet never reads) are skipped.
    const bool read_later = name.size() >= 8 && (name.compare(name.size() - 8, 8, "data.pkl") == 0 ||
                                                 name.find("/data/") != std::string::npos);
    // LibTorch's reader inflates the archive's version record itself when it opens the file, into a
    // buffer of the size the entry declares (a bomb declares 1 GiB); a version is a few digits.
    const bool version_record =
        name == "version" || (name.size() > 8 && name.compare(name.size() - 8, 8, "/version") == 0);
    const uint64_t declared = uncompressed32 == 0xFFFFFFFF ? ~uint64_t{0} : uncompressed32;
    if (version_record && (declared > 64 || compressed > 4096))
      throw Error(path, "zip entry '" + name + "' claims " + std::to_string(declared) +
                            " bytes; an archive's version record is a few digits (a zip bomb?)");
    if (method != 0 && !read_later) continue;
    if (method != 0 || compressed != (uncompressed32 == 0xFFFFFFFF ? compressed : uncompressed32))
      throw Error(path, "zip entry '" + name +
                            "' is compressed; torch.save and flatnet archives store it uncompressed "
                            "(was the file re-zipped by another tool?)");
    const auto lh = read_at(local, 30);
    if (little_endian(lh.data(), 4) != 0x04034b50) throw Error(path, "damaged zip archive (entry '" + name + "')");
    uint64_t data = local + 30 + little_endian(&lh[26], 2) + little_endian(&lh[28], 2);
    if (data + compressed > size) throw Error(path, "truncated zip archive (entry '" + name + "' runs past the end)");
    uLong c = crc32(0, nullptr, 0);
    in.seekg(static_cast<std::streamoff>(data));
    for (uint64_t left = compressed; left > 0;) {
      const auto n = static_cast<std::streamsize>(std::min<uint64_t>(left, chunk.size()));
      in.read(chunk.data(), n);
      if (!in) throw Error(path, "cannot read the zip archive");
      c = crc32(c, reinterpret_cast<const Bytef*>(chunk.data()), static_cast<uInt>(n));
      left -= static_cast<uint64_t>(n);
    }
    if (static_cast<uint32_t>(c) != crc)
      throw Error(path, "damaged file: zip entry '" + name +
                            "' fails its CRC-32 check (the bytes changed after it was written)");
  }
  return true;
}

ArchiveTopLevel read_archive_top_level(const std::filesystem::path& path) {
  const auto root = read_torchscript_archive(path);
  ArchiveTopLevel out;
  for (const auto& [k, v] : root->entries) {
    if (k->kind != PyValue::Kind::string) continue;
    const auto& key = k->text;
    if (v->kind == PyValue::Kind::string) out.text[key] = v->text;
    if (v->kind == PyValue::Kind::integer) out.integers[key] = v->integer;
    if (v->kind == PyValue::Kind::real) out.reals[key] = v->real;
    if (v->kind == PyValue::Kind::tensor) out.tensors[key] = v->tensor;
    if (v->is_dict())
      for (auto& [name, t] : tensors_in(*v)) out.tensor_dicts[key][name] = t;
  }
  return out;
}

}  // namespace flatnet
