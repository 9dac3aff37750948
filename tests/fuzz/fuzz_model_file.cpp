// A .flatnet model file, read as `flatnet infer --model` reads it: the stored spec (YAML), the
// camera, the provenance and every tensor against the architecture the spec builds.
#include "fuzz_common.hpp"
#include "nn/model_file.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto path = flatnet::fuzz::as_file(data, size, "model.flatnet");
  flatnet::fuzz::expect_clean([&] { (void)flatnet::load_model_file(path); });
  return 0;
}
