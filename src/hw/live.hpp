#pragma once
// Live view: grab the newest frame, preprocess it as the calibration expects, reconstruct
// (Tikhonov or a FlatNet model), show it with the frame rate on screen (or print the rate).
#include <iosfwd>

#include "io/camera_config.hpp"
#include "optics/camera_fit.hpp"
#include "hw/camera_device.hpp"
#include "hw/display.hpp"
#include "recon/reconstructor.hpp"

namespace flatnet {

struct LiveOptions {
  RawGeometry geometry;         // the camera's preprocessing (frame size checked against it)
  int64_t frames = 0;           // stop after this many frames (0: until Esc/q/Ctrl-C or `seconds`)
  double seconds = 0;           // stop after this long (0: no limit)
  std::ostream* log = nullptr;  // where to print the rate once a second (e.g. --no-window)
  // Whether the frames fit the camera the engine is for (optics/camera_fit.hpp): measured on the first
  // frame and then every `fit_seconds`; shown on screen, a misfit said once on `warn`. null: not judged.
  // A stream is one camera's frames: the last kFitWindow judged frames are also judged as a batch
  // (judge_batch), so a near twin's flat frame is flagged with its stream.
  const CameraFit* fit = nullptr;
  double fit_seconds = 1.0;
  bool require_fit = false;      // a frame that does not fit ends the view with an error instead
  std::ostream* warn = nullptr;  // where the misfit line goes (stderr)
};

constexpr size_t kFitWindow = 15;

struct LiveStats {
  int64_t frames = 0;
  double fps = 0;  // frames shown per second of wall time, end to end
  double grab_ms = 0, preprocess_ms = 0, reconstruct_ms = 0, show_ms = 0;  // means per frame
  int64_t fit_checks = 0, misfits = 0;  // frames whose camera fit was measured, and those that did not fit
  double worst_fit = 0;
};

// Each frame: preprocess as `options.geometry`, reconstruct one capture with `engine`, show.
LiveStats run_live(FrameSource& source, Reconstructor& engine, Display* display, const LiveOptions& options);

}  // namespace flatnet
