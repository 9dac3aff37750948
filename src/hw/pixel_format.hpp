#pragma once
// Camera pixel formats (GenICam PFNC names, as Aravis reports them) -> ADC codes, and codes ->
// the stored raw layout every other flatnet command reads (16-bit PNG of the Bayer mosaic with the
// ADC's bits shifted to the top, as FlatNet's Flea3 captures are). No Aravis here: pure functions,
// so the unpacking is tested byte for byte without a camera.
#include <cstdint>
#include <string>
#include <vector>

#include <torch/torch.h>

namespace flatnet {

enum class Packing {
  u8,          // one byte per pixel
  u16,         // little-endian 16-bit container, value LSB-aligned (Mono10, Mono12, Mono16, ...)
  lsb_packed,  // PFNC "...p" formats (Mono10p, BayerRG12p): a continuous LSB-first bit stream
  gev_packed   // GigE Vision legacy "...Packed" (Mono12Packed): 2 pixels in 3 bytes
};

struct PixelFormatInfo {
  std::string name;  // e.g. "BayerRG12p"
  int bits = 8;      // significant bits per pixel (the ADC's resolution)
  Packing packing = Packing::u8;
  std::string bayer;  // "BG", "GB", "GR", "RG", or "" for monochrome
  // Bytes a width x height frame occupies.
  int64_t frame_bytes(int64_t width, int64_t height) const;
};

// Describes a format flatnet can store faithfully, or throws an Error that says why not
// (colour-interpolated, YUV, floating point, > 16 bits) and lists what the camera should use.
PixelFormatInfo describe_pixel_format(const std::string& name);
// True when describe_pixel_format would accept it.
bool is_storable_pixel_format(const std::string& name);

// The frame's bytes -> {H,W} int32 ADC codes (0 .. 2^bits-1). Errors on a size mismatch.
torch::Tensor unpack_frame(const uint8_t* data, size_t size, int64_t width, int64_t height, const PixelFormatInfo& f);

// Mean ADC codes {H,W} (float64, fractional after averaging) -> stored 16-bit values
// round(codes * 2^(16-bits)), clamped to [0, 65535], as a uint16-range int32 tensor.
torch::Tensor codes_to_stored(const torch::Tensor& mean_codes, int bits);

// Test helpers: the inverse packings, so round trips can be checked (and fake frames made).
std::vector<uint8_t> pack_frame(const torch::Tensor& codes, const PixelFormatInfo& f);

}  // namespace flatnet
