// A calibration .mat through load_calibration, for a tiny camera (12x14 planes, 8-pixel scenes): full
// factors (P1b, Q1b, ...) or a compact shift-structured file (shift_rows, profile_rows, ...), whose
// profiles are expanded by the shifts the file states, and the factors' scale check.
#include "fuzz_common.hpp"
#include "io/camera_config.hpp"
#include "optics/camera.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto path = flatnet::fuzz::as_file(data, size, "calib.mat");
  flatnet::CameraConfig camera;
  camera.raw.raw_height = 32, camera.raw.raw_width = 32;
  camera.raw.crop = {0, 0, 12, 14};
  camera.scene_size = 8;
  flatnet::fuzz::expect_clean([&] { (void)flatnet::load_calibration(path, camera); });
  return 0;
}
