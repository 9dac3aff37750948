#include "io/mat_check.hpp"

#include <zlib.h>

#include <algorithm>
#include <cstring>
#include <vector>

#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet {
namespace {

constexpr uint32_t kMiMatrix = 14, kMiCompressed = 15;

uint32_t u32(const unsigned char* p) { return p[0] | p[1] << 8 | p[2] << 16 | static_cast<uint32_t>(p[3]) << 24; }

// Bytes per element of a v5 data type (0: not a numeric type).
uint64_t type_size(uint32_t type) {
  switch (type) {
    case 1:
    case 2:
      return 1;  // miINT8, miUINT8
    case 3:
    case 4:
      return 2;  // miINT16, miUINT16
    case 5:
    case 6:
    case 7:
      return 4;  // miINT32, miUINT32, miSINGLE
    case 9:
    case 12:
    case 13:
      return 8;  // miDOUBLE, miINT64, miUINT64
    default:
      return 0;
  }
}

// A data element's tag at p[0..8): {type, bytes, header size}; the small format packs <= 4 bytes of
// data into the tag itself.
struct Tag {
  uint32_t type;
  uint64_t bytes;
  uint64_t header;
};
Tag read_tag(const unsigned char* p) {
  const uint32_t first = u32(p);
  if (first >> 16) return {first & 0xffff, first >> 16, 4};
  return {first, u32(p + 4), 8};
}
uint64_t padded(uint64_t n) { return (n + 7) / 8 * 8; }
// The bytes a data element takes in the file, its tag included (a small element: its 8-byte tag).
uint64_t stored_size(const Tag& tag) { return tag.header == 4 ? 8 : 8 + padded(tag.bytes); }

void check_matrix(const unsigned char* m, uint64_t size, const std::filesystem::path& path, uint64_t max_bytes,
                  int depth = 0);

// The children of a cell or struct (`elements` miMATRIX elements from m[at]): matio makes one pointer
// per child when it lists the variable, before reading any of them, so a child needs its 8-byte tag
// in the file (found by scripts/fuzz.sh: a 384-byte struct claiming 2^28 elements made matio
// allocate 2 GB), and each child is checked as a variable is.
void check_children(const unsigned char* m, uint64_t size, uint64_t at, uint64_t elements, const std::string& where,
                    const std::filesystem::path& path, uint64_t max_bytes, int depth) {
  if (elements > (size - std::min(at, size)) / 8)
    throw Error(path, where + " declares " + std::to_string(elements) + " elements in " + std::to_string(size) +
                          " bytes (hostile or damaged file?)");
  for (uint64_t i = 0; i < elements; ++i) {
    require(at + 8 <= size, path, "damaged .mat file: " + where + "'s elements run past its end");
    const auto child = read_tag(m + at);
    require(child.header == 8 && child.type == kMiMatrix && child.bytes <= size - at - 8, path,
            "damaged .mat file: " + where + " holds an element that is not an array");
    if (child.bytes > 0) check_matrix(m + at + 8, child.bytes, path, max_bytes, depth + 1);
    at += stored_size(child);
  }
}

// Checks one miMATRIX element's contents `m` (size `size`, the bytes after its tag): flags,
// dimensions, name, then for numeric classes the real (and imaginary) data's byte counts, and for
// cells and structs their elements (nested at most 16 deep).
void check_matrix(const unsigned char* m, uint64_t size, const std::filesystem::path& path, uint64_t max_bytes,
                  int depth) {
  require(depth <= 16, path, "damaged .mat file: cells or structs nested more than 16 deep");
  auto need = [&](uint64_t at, uint64_t n, const char* what) {
    if (at + n > size) throw Error(path, std::string("damaged .mat file: a variable's ") + what + " runs past its end");
  };
  need(0, 16, "array flags");
  const auto flags = read_tag(m);
  require(flags.type == 6 && flags.bytes == 8, path, "damaged .mat file: a variable without array flags");
  const uint32_t cls = m[8] & 0xff;
  const bool complex = m[9] & 0x08;
  // Function handles (16), opaque objects (17) and unknown classes: matio makes one pointer per element
  // the dimensions claim before it reads any (found by scripts/fuzz.sh: a 376-byte function handle
  // claiming 6 x 69 M elements, a 3.3 GB malloc). flatnet reads none of them: refused.
  require(cls >= 1 && cls <= 15, path,
          "a variable of MATLAB class " + std::to_string(cls) +
              " (a function handle, an object or unknown); flatnet reads numeric arrays, text, cells and structs");
  uint64_t at = 16;
  need(at, 8, "dimensions");
  const auto dims = read_tag(m + at);
  require(dims.type == 5 && dims.bytes % 4 == 0 && dims.bytes >= 8 && dims.bytes <= 4 * 32, path,
          "damaged .mat file: a variable's dimensions are malformed");
  need(at + dims.header, dims.bytes, "dimensions");
  uint64_t count = 1;
  bool overflow = false;
  for (uint64_t i = 0; i < dims.bytes / 4; ++i) {
    const auto d = static_cast<int32_t>(u32(m + at + dims.header + 4 * i));
    if (d < 0) throw Error(path, "damaged .mat file: a negative dimension");
    overflow |= __builtin_mul_overflow(count, static_cast<uint64_t>(d), &count);
  }
  at += stored_size(dims);
  need(at, 8, "name");
  const auto name_tag = read_tag(m + at);
  need(at + name_tag.header, name_tag.bytes, "name");
  // Names are miINT8 (1) in every writer: a name of another type is read one way here and another
  // way by matio (found by scripts/fuzz.sh: a struct this check read as 0 fields, matio as 2^27).
  require(name_tag.type == 1, path, "damaged .mat file: a variable's name is not stored as text");
  const std::string name(reinterpret_cast<const char*>(m + at + name_tag.header), name_tag.bytes);
  at += stored_size(name_tag);
  const auto where = "variable '" + printable(name) + "'";  // a name from the file: escaped
  if (overflow && cls <= 4) throw Error(path, where + " declares more than 2^64 elements (hostile or damaged file?)");
  if (cls == 1) return check_children(m, size, at, count, where, path, max_bytes, depth);  // cell
  if (cls == 2 || cls == 3) {  // struct, object: (an object's class name), field name length, names
    if (cls == 3) {
      need(at, 8, "class name");
      const auto class_name = read_tag(m + at);
      at += stored_size(class_name);
    }
    need(at, 8, "field name length");
    const auto length_tag = read_tag(m + at);
    need(at + length_tag.header, 4, "field name length");
    require(length_tag.type == 5 && length_tag.bytes == 4, path,
            "damaged .mat file: " + where + "'s field name length is not one 32-bit integer");
    const uint64_t length = u32(m + at + length_tag.header);
    at += stored_size(length_tag);
    need(at, 8, "field names");
    const auto names = read_tag(m + at);
    need(at + names.header, names.bytes, "field names");
    require(names.type == 1 && (length == 0 ? names.bytes == 0 : names.bytes % length == 0), path,
            "damaged .mat file: " + where + "'s field names do not fill whole names of its field name length");
    const uint64_t fields = length == 0 ? 0 : names.bytes / length;
    at += stored_size(names);
    uint64_t elements = 0;
    if (__builtin_mul_overflow(count, fields, &elements))
      throw Error(path, where + " declares more than 2^64 fields (hostile or damaged file?)");
    return check_children(m, size, at, elements, where, path, max_bytes, depth);
  }
  if (cls == 4 && count > size)
    throw Error(path, where + " declares " + std::to_string(count) + " characters in " + std::to_string(size) +
                          " bytes (hostile or damaged file?)");
  if (cls < 6) return;  // chars, sparse: not read by flatnet
  if (overflow || count > max_bytes)
    throw Error(path, where + " declares " + (overflow ? std::string("more than 2^64") : std::to_string(count)) +
                          " values (hostile or damaged file?)");
  for (int part = 0; part < (complex ? 2 : 1); ++part) {
    need(at, 8, "data");
    const auto data = read_tag(m + at);
    const auto per = type_size(data.type);
    require(per > 0, path, where + " stores its data in an unknown type " + std::to_string(data.type));
    if (data.bytes != count * per)
      throw Error(path, where + "'s dimensions say " + std::to_string(count) + " values, its data holds " +
                            std::to_string(data.bytes / per) + " (damaged or hostile file)");
    if (data.bytes > max_bytes)
      throw Error(path, where + " holds " + std::to_string(data.bytes) + " bytes, more than the " +
                            std::to_string(max_bytes) + " its reader allows (not the file it expects?)");
    if (data.header + data.bytes > size - at)
      throw Error(path, "truncated: " + where + "'s data runs past the end of its element");
    at += stored_size(data);
  }
}

// Inflates a miCOMPRESSED element (at most `limit` bytes out): zlib checks the stream's own checksum.
std::string inflate_element(const unsigned char* p, uint64_t n, uint64_t limit, const std::filesystem::path& path) {
  z_stream z{};
  require(inflateInit(&z) == Z_OK, path, "cannot inflate a compressed variable");
  std::string out;
  std::vector<unsigned char> chunk(1 << 16);
  z.next_in = const_cast<unsigned char*>(p);
  z.avail_in = static_cast<uInt>(std::min<uint64_t>(n, UINT32_MAX));
  int rc = Z_OK;
  while (rc != Z_STREAM_END) {
    z.next_out = chunk.data();
    z.avail_out = static_cast<uInt>(chunk.size());
    rc = inflate(&z, Z_NO_FLUSH);
    if (rc != Z_OK && rc != Z_STREAM_END) {
      inflateEnd(&z);
      throw Error(path,
                  "damaged .mat file: a compressed variable does not inflate (zlib error " + std::to_string(rc) + ")");
    }
    out.append(reinterpret_cast<char*>(chunk.data()), chunk.size() - z.avail_out);
    if (out.size() > limit) {
      inflateEnd(&z);
      throw Error(path, "a compressed variable inflates past " + std::to_string(limit) +
                            " bytes, more than its reader allows (a zip bomb, or not the file expected here?)");
    }
    if (rc == Z_OK && z.avail_in == 0 && z.avail_out != 0) {
      inflateEnd(&z);
      throw Error(path, "truncated: a compressed variable ends early");
    }
  }
  inflateEnd(&z);
  return out;
}

void check_element(const unsigned char* p, uint64_t left, const std::filesystem::path& path, bool inside_compressed,
                   uint64_t max_bytes, uint64_t& used) {
  require(left >= 8, path, "truncated .mat file: an element's tag is cut short");
  const auto tag = read_tag(p);
  require(tag.header == 8, path, "damaged .mat file: a top-level element in the small format");
  if (tag.bytes > left - 8)
    throw Error(path, "truncated: a .mat element claims " + std::to_string(tag.bytes) + " bytes, " +
                          std::to_string(left - 8) + " remain");
  used = 8 + (tag.type == kMiCompressed ? tag.bytes : padded(tag.bytes));
  used = std::min(used, left);
  if (tag.type == kMiMatrix) check_matrix(p + 8, tag.bytes, path, max_bytes);
  if (tag.type == kMiCompressed && !inside_compressed) {
    // zlib's deflate shrinks at most ~1032:1, so more than that out of these bytes is a bomb; and no
    // variable inflates past what its reader allows, with room for its headers (name, dimensions).
    constexpr uint64_t kHeaders = 64 << 10;
    const uint64_t limit =
        std::min<uint64_t>(std::min(kMaxMatVariableBytes, max_bytes) + kHeaders, 1100 * tag.bytes + kHeaders);
    const auto inner = inflate_element(p + 8, tag.bytes, limit, path);
    uint64_t inner_used = 0;
    check_element(reinterpret_cast<const unsigned char*>(inner.data()), inner.size(), path, true, max_bytes,
                  inner_used);
  }
}

}  // namespace

void check_mat5_sizes(const std::string& bytes, const std::filesystem::path& path, uint64_t max_variable_bytes) {
  require(bytes.size() >= 128, path, "not a readable MATLAB .mat file (shorter than its 128-byte header)");
  const auto* p = reinterpret_cast<const unsigned char*>(bytes.data());
  // Both versions open with the text "MATLAB": matio reads a file whose header it does not take as
  // v5 or v7.3 as MATLAB v4, whose first bytes are sizes ("MATL" as a name length: a 1.3 GB malloc,
  // found by scripts/fuzz.sh), so only a v5 or v7.3 header reaches it.
  require(bytes.compare(0, 6, "MATLAB") == 0, path,
          "not a MATLAB v5 or v7.3 .mat file (its header does not begin with \"MATLAB\"; flatnet reads v5 and v7.3)");
  const uint16_t version = p[124] | p[125] << 8;
  if (version == 0x0200) {  // v7.3: an HDF5 file behind a 512-byte user block (HDF5's own checks)
    require(bytes.size() >= 520 && bytes.compare(512, 8, "\x89HDF\r\n\x1a\n") == 0, path,
            "claims MATLAB v7.3 but holds no HDF5 file after its 512-byte header");
    return;
  }
  require(
      version == 0x0100 && p[126] == 'I' && p[127] == 'M', path,
      "not a little-endian MATLAB v5 .mat file (flatnet reads v5 and v7.3 files written on little-endian machines)");
  for (uint64_t at = 128; at < bytes.size();) {
    uint64_t used = 0;
    check_element(p + at, bytes.size() - at, path, false, max_variable_bytes, used);
    at += used;
  }
}

}  // namespace flatnet
