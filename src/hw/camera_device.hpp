#pragma once
// Machine-vision cameras through Aravis (GenICam: USB3 Vision, GigE Vision, and Aravis's built-in
// fake camera). A FrameSource hands out complete frames as ADC codes; everything above it
// (averaging, datasets, live view) is camera-agnostic and testable with any source.
#include <array>
#include <chrono>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <torch/torch.h>

#include "hw/pixel_format.hpp"

namespace flatnet {

struct DeviceInfo {
  std::string id, vendor, model, serial, protocol, address;
};

// Every camera Aravis can see; with include_fake, also its built-in fake camera ("Fake_1").
std::vector<DeviceInfo> list_cameras(bool include_fake);
// "fake" -> Aravis's built-in fake camera id (and enables its interface); other ids unchanged.
std::string resolve_device_id(const std::string& id);

struct DeviceSettings {
  std::string pixel_format;                      // empty: keep the camera's (checked storable)
  std::optional<double> exposure_us;             // ExposureTime
  std::optional<double> gain_db;                 // Gain
  std::optional<double> frame_rate;              // AcquisitionFrameRate
  std::optional<std::array<int64_t, 4>> region;  // x, y, width, height (sensor pixels)
  int64_t packet_size = 0;                       // GigE Vision: 0 = negotiate the largest that passes
  int timeout_ms = 2000;                         // per frame
  int retries = 3;                               // failed frames (timeout, incomplete) before giving up
  int buffers = 8;                               // stream buffers queued in the driver
};

struct Frame {
  torch::Tensor codes;  // {H,W} int32 ADC codes
  uint64_t frame_id = 0;
  int64_t timestamp_ns = 0;  // host (wall-clock) time the frame arrived
};

class FrameSource {
 public:
  using Clock = std::chrono::system_clock;
  virtual ~FrameSource() = default;
  // The next complete frame that arrived at or after `not_before`; frames queued earlier (e.g.
  // exposed while a display was still changing) are dropped. Retries failures, then throws.
  virtual Frame next_frame(Clock::time_point not_before) = 0;
  // The newest complete frame, dropping any backlog (live view).
  virtual Frame latest_frame() = 0;
  virtual const PixelFormatInfo& format() const = 0;
  // Device and settings as read back from the camera (for capture sidecars).
  virtual nlohmann::json describe() const = 0;
  // Failures recovered from so far (timeouts, incomplete buffers, reconnections).
  virtual int64_t recovered_failures() const = 0;
};

// Opens a camera by id (see list_cameras; "fake" for the built-in fake camera), applies the
// settings and starts continuous acquisition. Errors name the device and the setting at fault.
std::unique_ptr<FrameSource> open_camera(const std::string& id, const DeviceSettings& settings);

// Whether this build has Aravis (FLATNET_WITH_ARAVIS).
bool have_aravis();

}  // namespace flatnet
