// safetensors bytes (model files and checkpoints are safetensors): the header's JSON, its offsets,
// dtypes and shapes, the CRC extension.
#include "fuzz_common.hpp"
#include "io/safetensors.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string bytes(reinterpret_cast<const char*>(data), size);
  flatnet::fuzz::expect_clean([&] {
    const auto st = flatnet::parse_safetensors(bytes, "fuzz.safetensors");
    for (const auto& [name, tensor] : st.tensors) (void)tensor.sum();
  });
  return 0;
}
