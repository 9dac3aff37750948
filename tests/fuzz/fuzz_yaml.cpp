// YAML text: a training config (with every key's range checked) and a camera file.
#include "fuzz_common.hpp"
#include "io/camera_config.hpp"
#include "io/config.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  flatnet::fuzz::expect_clean([&] { (void)flatnet::Config::from_text(text, "fuzz.yaml").to_yaml(); });
  flatnet::fuzz::expect_clean([&] { (void)flatnet::camera_from_yaml_text(text, "camera.yaml"); });
  return 0;
}
