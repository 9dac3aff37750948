#include "io/image.hpp"

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <opencv2/imgproc.hpp>
#include <zlib.h>

#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet {

namespace {

// Decoder messages on one line: OIIO joins libpng's and libjpeg's with newlines.
std::string one_line(std::string text) {
  for (auto& ch : text)
    if (ch == '\n' || ch == '\r') ch = ';';
  while (!text.empty() && (text.back() == ';' || text.back() == ' ')) text.pop_back();
  return text;
}

// Far above any capture or photograph, far below what would exhaust memory: a "decompression bomb"
// (a tiny file that declares a gigapixel image) is refused before anything is allocated.
constexpr int64_t kMaxImageValues = int64_t{1} << 28;  // width x height x channels
constexpr double kMaxExpansion = 4096;                 // decoded samples' bytes per byte of file, at most

uint32_t big_endian32(const unsigned char* p) { return (uint32_t{p[0]} << 24) | (p[1] << 16) | (p[2] << 8) | p[3]; }

// What the decoders let through silently: libjpeg fills a truncated JPEG with grey, and a PNG chunk
// with a bad CRC, or a file cut short, reaches libpng (which prints to stderr on its own). PNG:
// every chunk's CRC and the IEND chunk; JPEG: its start and end markers.
void check_container(const std::filesystem::path& path, const std::vector<char>& bytes) {
  const auto* b = reinterpret_cast<const unsigned char*>(bytes.data());
  const size_t n = bytes.size();
  static const unsigned char png_magic[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  if (n >= 8 && std::equal(png_magic, png_magic + 8, b)) {
    size_t at = 8;
    bool ended = false;
    while (!ended) {
      require(at + 12 <= n, path, "truncated PNG (the file ends inside a chunk, before IEND)");
      const uint32_t length = big_endian32(b + at);
      require(length <= n && at + 12 + length <= n, path, "truncated PNG (the file ends inside a chunk, before IEND)");
      const std::string type(reinterpret_cast<const char*>(b + at + 4), 4);
      const uint32_t crc = big_endian32(b + at + 8 + length);
      require(static_cast<uint32_t>(crc32(0, b + at + 4, length + 4)) == crc, path,
              "damaged PNG (chunk " + type + " at byte " + std::to_string(at) + " fails its CRC)");
      if (type == "IHDR" && length >= 8) {
        const int64_t w = big_endian32(b + at + 8), h = big_endian32(b + at + 12);
        require(w * h <= kMaxImageValues, path,
                "declares a " + std::to_string(w) + "x" + std::to_string(h) + " image, beyond flatnet's limit of " +
                    std::to_string(kMaxImageValues) + " pixels (a damaged file or a decompression bomb)");
      }
      ended = type == "IEND";
      at += 12 + length;
    }
    return;
  }
  if (n >= 2 && b[0] == 0xFF && b[1] == 0xD8) {  // JPEG: SOI ... EOI (a few trailing bytes are allowed)
    bool has_end = false;
    const size_t search_from = n > 4096 ? n - 4096 : 2;
    for (size_t i = search_from; i + 1 < n && !has_end; ++i) has_end = b[i] == 0xFF && b[i + 1] == 0xD9;
    require(has_end, path, "truncated JPEG (no end-of-image marker; the decoder would fill the rest with grey)");
  }
}

// An image file read once: its bytes are checked (check_container), then decoded from memory.
struct OpenedImage {
  std::vector<char> bytes;
  std::unique_ptr<OIIO::Filesystem::IOMemReader> memory;  // must outlive `in`
  std::unique_ptr<OIIO::ImageInput> in;
  OIIO::ImageInput* operator->() const { return in.get(); }
};

OpenedImage open_input(const std::filesystem::path& path) {
  require(std::filesystem::exists(path), path, "no such file");
  require(!std::filesystem::is_directory(path), path, "is a folder, not an image");
  OpenedImage image;
  image.bytes = read_bytes(path);
  check_container(path, image.bytes);
  image.memory = std::make_unique<OIIO::Filesystem::IOMemReader>(image.bytes.data(), image.bytes.size());
  image.in = OIIO::ImageInput::open(path.string(), nullptr, image.memory.get());
  if (!image.in) image.in = OIIO::ImageInput::open(path.string());  // a reader without memory input
  auto& in = image.in;
  require(in != nullptr, path, "unreadable image (" + one_line(OIIO::geterror()) + ")");
  const auto& spec = in->spec();
  const auto size =
      std::to_string(spec.width) + "x" + std::to_string(spec.height) + "x" + std::to_string(spec.nchannels);
  // Sizes come from the file: a width past 2^31 reads back negative (found by scripts/fuzz.sh: a TIFF
  // of width 0x80000040), so each is checked positive before any product of them.
  require(spec.width > 0 && spec.height > 0 && spec.nchannels >= 1, path,
          "a " + size + " image: an empty or impossible size (a damaged file)");
  const int64_t values = int64_t{spec.width} * spec.height * spec.nchannels;
  require(values <= kMaxImageValues, path,
          "a " + size + " image is beyond flatnet's limit (a damaged file or a decompression bomb)");
  // Compression has a ceiling: deflate (PNG, TIFF) decodes to at most ~1032x its stream and TIFF's
  // LZW to ~2700x, so a file whose header claims more than 4096x its own size of samples cannot hold
  // that image. Refused before a buffer of the claimed size is made (found by scripts/fuzz.sh: a
  // 600-byte TIFF claiming 1.1 GB of samples).
  const double holdable_bytes = kMaxExpansion * static_cast<double>(image.bytes.size()) + (1 << 20);
  const double sample_bytes = static_cast<double>(spec.format.size());
  require(static_cast<double>(values) * sample_bytes <= holdable_bytes, path,
          "claims a " + size + " image in " + std::to_string(image.bytes.size()) +
              " bytes, more than any compression holds (a damaged file or a decompression bomb)");
  // OIIO reads a TIFF a strip at a time into a buffer of RowsPerStrip scanlines, taking the tag as
  // written even when it exceeds the image's height (found by scripts/fuzz.sh: a 181-byte TIFF of 64
  // columns claiming 18.6 M rows per strip made a 2.4 GB buffer). The strip's bytes are held to the
  // same bound as the image's.
  const int64_t rows_per_strip = spec.get_int_attribute("tiff:RowsPerStrip", 0);
  const double strip_bytes = static_cast<double>(rows_per_strip) * spec.width * spec.nchannels * sample_bytes;
  require(rows_per_strip <= spec.height || strip_bytes <= holdable_bytes, path,
          "claims " + std::to_string(rows_per_strip) + " rows per strip in a " + std::to_string(spec.height) +
              "-row image of " + std::to_string(image.bytes.size()) + " bytes (a damaged file)");
  return image;
}

}  // namespace

torch::Tensor read_rgb(const std::filesystem::path& path) {
  auto in = open_input(path);
  const auto& spec = in->spec();
  const int w = spec.width, h = spec.height, c = spec.nchannels;
  require(w > 0 && h > 0 && c >= 1, path, "empty image");
  auto buf = torch::empty({h, w, c}, torch::kFloat32);
  // Reading as FLOAT normalises integer formats to [0,1] (8-bit /255, 16-bit /65535).
  const bool ok = in->read_image(0, 0, 0, c, OIIO::TypeDesc::FLOAT, buf.data_ptr<float>());
  in->close();
  require(ok, path, "corrupt or truncated image (" + one_line(in->geterror()) + ")");
  auto chw = buf.permute({2, 0, 1});
  if (c == 1 || c == 2)
    chw = chw.slice(0, 0, 1).expand({3, h, w});
  else
    chw = chw.slice(0, 0, 3);
  return chw.contiguous().clamp(0.0, 1.0);
}

ImageHeader read_image_header(const std::filesystem::path& path) {
  auto in = open_input(path);
  const auto& spec = in->spec();
  ImageHeader h{spec.width, spec.height, spec.nchannels, static_cast<int>(8 * spec.format.size())};
  in->close();
  return h;
}

torch::Tensor read_gray16(const std::filesystem::path& path) {
  auto in = open_input(path);
  const auto& spec = in->spec();
  require(spec.nchannels == 1, path,
          "raw capture must be single-channel (Bayer mosaic), found " + std::to_string(spec.nchannels) + " channels");
  require(spec.format == OIIO::TypeDesc::UINT16, path,
          "raw capture must be 16-bit, found " + std::string(spec.format.c_str()));
  auto buf = torch::empty({spec.height, spec.width}, torch::kInt32);
  std::vector<uint16_t> raw(static_cast<size_t>(spec.height) * spec.width);
  const bool ok = in->read_image(0, 0, 0, 1, OIIO::TypeDesc::UINT16, raw.data());
  in->close();
  require(ok, path, "corrupt or truncated image (" + one_line(in->geterror()) + ")");
  auto* dst = buf.data_ptr<int32_t>();
  for (size_t i = 0; i < raw.size(); ++i) dst[i] = raw[i];
  return buf;
}

namespace {

// Encodes in memory, then writes the bytes with every write checked: OIIO's file writers do not
// report a full disk (a truncated PNG was renamed into place and the run reported success).
void write_image(const std::filesystem::path& path, const void* data, int w, int h, int c, OIIO::TypeDesc type) {
  auto out = OIIO::ImageOutput::create(path.string());
  require(out != nullptr, path, "no image writer for this extension");
  std::vector<unsigned char> encoded;
  OIIO::Filesystem::IOVecOutput memory(encoded);
  require(out->supports("ioproxy") && out->set_ioproxy(&memory), path,
          "this image format cannot be written through memory");
  OIIO::ImageSpec spec(w, h, c, type);
  require(out->open(path.string(), spec), path, "cannot encode (" + out->geterror() + ")");
  const bool ok = out->write_image(type, data);
  const bool closed = out->close();
  require(ok && closed, path, "cannot encode (" + out->geterror() + ")");
  write_bytes_atomically(path, std::string(encoded.begin(), encoded.end()));
}

}  // namespace

void write_rgb8(const std::filesystem::path& path, const torch::Tensor& rgb) {
  TORCH_CHECK(rgb.dim() == 3 && rgb.size(0) == 3, "write_rgb8 expects {3,H,W}, got ", rgb.sizes());
  auto hwc =
      (rgb.detach().to(torch::kFloat32).clamp(0, 1) * 255.0f).round().to(torch::kUInt8).permute({1, 2, 0}).contiguous();
  write_image(path, hwc.data_ptr<uint8_t>(), static_cast<int>(rgb.size(2)), static_cast<int>(rgb.size(1)), 3,
              OIIO::TypeDesc::UINT8);
}

void write_gray16(const std::filesystem::path& path, const torch::Tensor& codes) {
  TORCH_CHECK(codes.dim() == 2, "write_gray16 expects {H,W}, got ", codes.sizes());
  auto c = codes.detach().to(torch::kInt32).clamp(0, 65535).contiguous();
  std::vector<uint16_t> data(c.numel());
  const auto* src = c.data_ptr<int32_t>();
  for (size_t i = 0; i < data.size(); ++i) data[i] = static_cast<uint16_t>(src[i]);
  write_image(path, data.data(), static_cast<int>(c.size(1)), static_cast<int>(c.size(0)), 1, OIIO::TypeDesc::UINT16);
}

torch::Tensor resize(const torch::Tensor& chw, int64_t h, int64_t w) {
  TORCH_CHECK(chw.dim() == 3, "resize expects {C,H,W}");
  if (chw.size(1) == h && chw.size(2) == w) return chw;
  auto hwc = chw.to(torch::kFloat32).permute({1, 2, 0}).contiguous();
  const int c = static_cast<int>(chw.size(0));
  cv::Mat src(static_cast<int>(chw.size(1)), static_cast<int>(chw.size(2)), CV_32FC(c), hwc.data_ptr<float>());
  cv::Mat dst;
  const bool shrinking = h < chw.size(1) || w < chw.size(2);
  cv::resize(src, dst, cv::Size(static_cast<int>(w), static_cast<int>(h)), 0, 0,
             shrinking ? cv::INTER_AREA : cv::INTER_LINEAR);
  auto out = torch::from_blob(dst.data, {h, w, c}, torch::kFloat32).clone();
  return out.permute({2, 0, 1}).contiguous();
}

torch::Tensor srgb_to_linear(const torch::Tensor& x) {
  return torch::where(x <= 0.04045, x / 12.92, torch::pow((x + 0.055) / 1.055, 2.4));
}

torch::Tensor linear_to_srgb(const torch::Tensor& x) {
  auto c = x.clamp(0.0, 1.0);
  return torch::where(c <= 0.0031308, c * 12.92, 1.055 * torch::pow(c, 1.0 / 2.4) - 0.055);
}

torch::Tensor display_to_light(const torch::Tensor& x, double gamma) {
  return gamma > 0 ? torch::pow(x.clamp_min(0.0), gamma) : srgb_to_linear(x);
}

torch::Tensor light_to_display(const torch::Tensor& x, double gamma) {
  return gamma > 0 ? torch::pow(x.clamp(0.0, 1.0), 1.0 / gamma) : linear_to_srgb(x);
}

torch::Tensor bayer_planes_to_rgb(const torch::Tensor& planes) {
  // planes: {..,4,H,W} (b, gb, gr, r) -> {..,3,H,W} (R, G, B)
  auto b = planes.select(-3, 0), gb = planes.select(-3, 1), gr = planes.select(-3, 2), r = planes.select(-3, 3);
  return torch::stack({r, 0.5 * (gb + gr), b}, -3);
}

torch::Tensor unmix_primaries(const torch::Tensor& planes, const torch::Tensor& mix) {
  const auto unmix = torch::linalg_pinv(mix.to(torch::kFloat64)).to(planes.scalar_type());  // {3,4}
  return torch::einsum("kc,...chw->...khw", {unmix, planes});
}

torch::Tensor colour_mix_matrix(const std::vector<std::array<double, 3>>& rows) {
  auto mix = torch::empty({static_cast<int64_t>(rows.size()), 3}, torch::kFloat64);
  auto m = mix.accessor<double, 2>();
  for (size_t p = 0; p < rows.size(); ++p)
    for (size_t k = 0; k < 3; ++k) m[static_cast<int64_t>(p)][static_cast<int64_t>(k)] = rows[p][k];
  return mix;
}

std::vector<std::array<double, 3>> colour_mix_rows(const torch::Tensor& mix) {
  const auto m = mix.to(torch::kFloat64).contiguous();
  const auto a = m.accessor<double, 2>();
  std::vector<std::array<double, 3>> rows;
  for (int64_t p = 0; p < m.size(0); ++p) rows.push_back({a[p][0], a[p][1], a[p][2]});
  return rows;
}

torch::Tensor planes_to_srgb(const torch::Tensor& planes) {
  return linear_to_srgb(bayer_planes_to_rgb(planes).clamp(0, 1));
}

torch::Tensor rgb_to_bayer_planes(const torch::Tensor& rgb) {
  auto R = rgb.select(-3, 0), G = rgb.select(-3, 1), B = rgb.select(-3, 2);
  return torch::stack({B, G, G, R}, -3);
}

}  // namespace flatnet
