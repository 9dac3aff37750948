#include "hw/pixel_format.hpp"

#include "core/error.hpp"

namespace flatnet {

namespace {

const char* kStorableHint =
    "flatnet stores the raw sensor mosaic; choose a Mono or Bayer format of 8 to 16 bits "
    "(Mono8, Mono10/12/14/16, Mono10p/12p, Mono10Packed/12Packed, Bayer??8, Bayer??10/12/16, Bayer??10p/12p, "
    "Bayer??12Packed)";

bool starts_with(const std::string& s, const std::string& prefix) { return s.rfind(prefix, 0) == 0; }

}  // namespace

int64_t PixelFormatInfo::frame_bytes(int64_t width, int64_t height) const {
  const int64_t n = width * height;
  switch (packing) {
    case Packing::u8:
      return n;
    case Packing::u16:
      return 2 * n;
    case Packing::lsb_packed:
      return (n * bits + 7) / 8;
    case Packing::gev_packed:
      return (n + 1) / 2 * 3;
  }
  return 0;
}

PixelFormatInfo describe_pixel_format(const std::string& name) {
  PixelFormatInfo f;
  f.name = name;
  std::string rest;
  if (starts_with(name, "Mono")) {
    rest = name.substr(4);
  } else if (starts_with(name, "Bayer") && name.size() > 7) {
    f.bayer = name.substr(5, 2);
    require(f.bayer == "BG" || f.bayer == "GB" || f.bayer == "GR" || f.bayer == "RG", name,
            std::string("unknown Bayer pattern; ") + kStorableHint);
    rest = name.substr(7);
  } else {
    throw Error(name +
                ": not a raw mosaic format (colour-interpolated, YUV or packed colour images lose the "
                "Bayer planes the calibration refers to); " +
                kStorableHint);
  }
  // rest: "8", "10", "12", "14", "16", "10p", "12p", "10Packed", "12Packed"
  size_t digits = 0;
  while (digits < rest.size() && std::isdigit(static_cast<unsigned char>(rest[digits]))) ++digits;
  require(digits > 0 && digits <= 2, name, std::string("unrecognised pixel format; ") + kStorableHint);
  f.bits = std::stoi(rest.substr(0, digits));
  const std::string suffix = rest.substr(digits);
  require(f.bits >= 8 && f.bits <= 16, name,
          std::to_string(f.bits) + "-bit pixels do not fit a 16-bit PNG without loss; " + kStorableHint);
  if (suffix.empty()) {
    f.packing = f.bits == 8 ? Packing::u8 : Packing::u16;
  } else if (suffix == "p") {
    f.packing = f.bits == 8 ? Packing::u8 : (f.bits == 16 ? Packing::u16 : Packing::lsb_packed);
  } else if (suffix == "Packed" && (f.bits == 10 || f.bits == 12)) {
    f.packing = Packing::gev_packed;
  } else {
    throw Error(name + ": unsupported packing '" + suffix + "'; " + kStorableHint);
  }
  return f;
}

bool is_storable_pixel_format(const std::string& name) {
  try {
    describe_pixel_format(name);
    return true;
  } catch (const Error&) {
    return false;
  }
}

torch::Tensor unpack_frame(const uint8_t* data, size_t size, int64_t width, int64_t height, const PixelFormatInfo& f) {
  const int64_t expected = f.frame_bytes(width, height);
  require(static_cast<int64_t>(size) >= expected, f.name,
          "incomplete frame: " + std::to_string(size) + " bytes for a " + std::to_string(width) + "x" +
              std::to_string(height) + " image that needs " + std::to_string(expected));
  const int64_t n = width * height;
  auto out = torch::empty({height, width}, torch::kInt32);
  int32_t* o = out.data_ptr<int32_t>();
  const int32_t mask = (1 << f.bits) - 1;
  switch (f.packing) {
    case Packing::u8:
      for (int64_t i = 0; i < n; ++i) o[i] = data[i];
      break;
    case Packing::u16:  // GenICam transports are little-endian
      for (int64_t i = 0; i < n; ++i) o[i] = (data[2 * i] | (data[2 * i + 1] << 8)) & mask;
      break;
    case Packing::lsb_packed: {  // pixel i occupies bits [i*bits, (i+1)*bits) of the stream, LSB first
      for (int64_t i = 0; i < n; ++i) {
        const int64_t bit = i * f.bits;
        const int64_t byte = bit / 8;
        uint32_t word = data[byte];
        if (byte + 1 < expected) word |= static_cast<uint32_t>(data[byte + 1]) << 8;
        if (byte + 2 < expected) word |= static_cast<uint32_t>(data[byte + 2]) << 16;
        o[i] = static_cast<int32_t>((word >> (bit % 8)) & mask);
      }
      break;
    }
    case Packing::gev_packed: {
      // GigE Vision 2.0, "Mono12Packed": B0 = p0[11:4], B1 = p1[3:0]<<4 | p0[3:0], B2 = p1[11:4].
      // "Mono10Packed": B0 = p0[9:2], B1 = p1[1:0]<<4 | p0[1:0], B2 = p1[9:2].
      const int low = f.bits - 8;
      const int low_mask = (1 << low) - 1;
      for (int64_t i = 0; i < n; i += 2) {
        const uint8_t* b = data + i / 2 * 3;
        o[i] = (b[0] << low) | (b[1] & low_mask);
        if (i + 1 < n) o[i + 1] = (b[2] << low) | ((b[1] >> 4) & low_mask);
      }
      break;
    }
  }
  return out;
}

std::vector<uint8_t> pack_frame(const torch::Tensor& codes, const PixelFormatInfo& f) {
  auto c = codes.to(torch::kInt32).contiguous();
  const int32_t* p = c.data_ptr<int32_t>();
  const int64_t n = c.numel();
  std::vector<uint8_t> out(static_cast<size_t>(f.frame_bytes(c.size(1), c.size(0))), 0);
  switch (f.packing) {
    case Packing::u8:
      for (int64_t i = 0; i < n; ++i) out[i] = static_cast<uint8_t>(p[i]);
      break;
    case Packing::u16:
      for (int64_t i = 0; i < n; ++i) out[2 * i] = p[i] & 0xff, out[2 * i + 1] = (p[i] >> 8) & 0xff;
      break;
    case Packing::lsb_packed:
      for (int64_t i = 0; i < n; ++i)
        for (int k = 0; k < f.bits; ++k)
          if ((p[i] >> k) & 1) out[(i * f.bits + k) / 8] |= static_cast<uint8_t>(1 << ((i * f.bits + k) % 8));
      break;
    case Packing::gev_packed: {
      const int low = f.bits - 8;
      const int low_mask = (1 << low) - 1;
      for (int64_t i = 0; i < n; i += 2) {
        uint8_t* b = out.data() + i / 2 * 3;
        b[0] = static_cast<uint8_t>(p[i] >> low);
        b[1] = static_cast<uint8_t>(p[i] & low_mask);
        if (i + 1 < n) {
          b[2] = static_cast<uint8_t>(p[i + 1] >> low);
          b[1] |= static_cast<uint8_t>((p[i + 1] & low_mask) << 4);
        }
      }
      break;
    }
  }
  return out;
}

torch::Tensor codes_to_stored(const torch::Tensor& mean_codes, int bits) {
  const double scale = static_cast<double>(1 << (16 - bits));
  return torch::round(mean_codes.to(torch::kFloat64) * scale).clamp(0, 65535).to(torch::kInt32);
}

}  // namespace flatnet
