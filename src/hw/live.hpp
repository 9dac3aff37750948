#pragma once
// Live view: grab the newest frame, preprocess it as the calibration expects, reconstruct
// (Tikhonov or a FlatNet model), show it with the frame rate on screen (or print the rate).
#include <iosfwd>

#include "io/camera_config.hpp"
#include "hw/camera_device.hpp"
#include "hw/display.hpp"
#include "recon/reconstructor.hpp"

namespace flatnet {

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

// Each frame: preprocess as `options.geometry`, reconstruct one capture with `engine`, show.
LiveStats run_live(FrameSource& source, Reconstructor& engine, Display* display, const LiveOptions& options);

}  // namespace flatnet
