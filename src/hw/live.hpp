#pragma once
// Live view: grab the newest frame, preprocess it as the calibration expects, reconstruct
// (Tikhonov or a FlatNet model), show it with the frame rate on screen (or print the rate).
#include <functional>
#include <iosfwd>

#include "core/camera_config.hpp"
#include "hw/camera_device.hpp"
#include "hw/display.hpp"

namespace flatnet {

// Measurement planes {4,h,w} -> sRGB image {3,N,N} in [0,1].
using Reconstructor = std::function<torch::Tensor(const torch::Tensor& planes)>;

struct LiveOptions {
  RawGeometry geometry;         // the camera's preprocessing (frame size checked against it)
  int64_t frames = 0;           // stop after this many frames (0: until Esc/q/Ctrl-C or `seconds`)
  double seconds = 0;           // stop after this long (0: no limit)
  std::ostream* log = nullptr;  // where to print the rate once a second (e.g. --no-window)
};

struct LiveStats {
  int64_t frames = 0;
  double fps = 0;  // frames shown per second of wall time, end to end
  double grab_ms = 0, preprocess_ms = 0, reconstruct_ms = 0, show_ms = 0;  // means per frame
};

// Camera codes {H,W} -> raw frame in [0,1] as a stored capture would read back (codes_to_stored / 65535).
torch::Tensor codes_to_unit(const torch::Tensor& codes, int bits);

LiveStats run_live(FrameSource& source, const Reconstructor& reconstruct, Display* display, const LiveOptions& options);

}  // namespace flatnet
