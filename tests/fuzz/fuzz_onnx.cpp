// An ONNX file, read as `flatnet infer --engine opencv` reads its camera and sizes before OpenCV does.
#include "fuzz_common.hpp"
#include "nn/onnx_export.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto path = flatnet::fuzz::as_file(data, size, "model.onnx");
  flatnet::fuzz::expect_clean([&] { (void)flatnet::read_onnx_info(path); });
  return 0;
}
