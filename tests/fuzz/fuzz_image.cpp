// Captures and photographs: a raw 16-bit capture and an 8-bit photograph, as PNG or TIFF (the first
// byte chooses the extension OpenImageIO goes by).
#include "fuzz_common.hpp"
#include "io/image.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size == 0) return 0;
  const auto path = flatnet::fuzz::as_file(data + 1, size - 1, data[0] % 2 ? "capture.tif" : "capture.png");
  flatnet::fuzz::expect_clean([&] { (void)flatnet::read_gray16(path); });
  flatnet::fuzz::expect_clean([&] { (void)flatnet::read_rgb(path); });
  flatnet::fuzz::expect_clean([&] { (void)flatnet::read_image_header(path); });
  return 0;
}
