// A training checkpoint, read as `flatnet train --resume` first reads it: the run id, the best PSNR,
// the config and the camera it records.
#include "fuzz_common.hpp"
#include "nn/checkpoint.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto path = flatnet::fuzz::as_file(data, size, "latest.ckpt");
  flatnet::fuzz::expect_clean([&] { (void)flatnet::checkpoint_settings(path); });
  return 0;
}
