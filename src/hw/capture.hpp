#pragma once
// Direct captures: frames from a FrameSource -> averaged ADC codes -> raw 16-bit PNGs (the
// layout `load_capture` reads: Bayer mosaic, the ADC's bits shifted to the top) + JSON sidecars.
#include <filesystem>
#include <string>

#include <nlohmann/json.hpp>

#include "core/util.hpp"  // watch_interrupts, interrupted
#include "hw/camera_device.hpp"

namespace flatnet {

// Mean of k complete frames that all arrived at or after not_before: {H,W} float64 ADC codes.
// `ids` (optional) receives the frame ids used.
torch::Tensor average_frames(FrameSource& source, int k, FrameSource::Clock::time_point not_before,
                             std::vector<uint64_t>* ids = nullptr);

// Writes `png` (16-bit: round(mean * 2^(16-bits))) and the sidecar `png` with .json, each
// atomically, the PNG last: a PNG on disk always has its sidecar and is never partial.
void write_raw_capture(const std::filesystem::path& png, const torch::Tensor& mean_codes, const PixelFormatInfo& format,
                       const nlohmann::json& sidecar);

// The sidecar for one averaged capture: the device description plus what was averaged.
nlohmann::json capture_sidecar(const FrameSource& source, int average, const std::vector<uint64_t>& ids);

struct CaptureOptions {
  std::filesystem::path out;  // folder; files are PREFIX_0000.png, numbering after existing ones
  std::string prefix = "capture";
  int frames = 1;   // captures to write
  int average = 1;  // frames averaged into each capture
  bool progress = true;
};

struct CaptureReport {
  int64_t written = 0;
  int64_t first_index = 0;
  double seconds = 0;
  double frames_per_s = 0;  // camera frames consumed per second (averaging included)
};

CaptureReport capture_frames(FrameSource& source, const CaptureOptions& options);

}  // namespace flatnet
