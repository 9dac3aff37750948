// A MATLAB .mat file (calibrations, rigs, codes), through matio: every variable listed and read.
#include "fuzz_common.hpp"
#include "io/mat.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto path = flatnet::fuzz::as_file(data, size, "calib.mat");
  flatnet::fuzz::expect_clean([&] {
    flatnet::MatReader mat(path);
    for (const auto& name : mat.names()) (void)mat.read(name);
  });
  return 0;
}
