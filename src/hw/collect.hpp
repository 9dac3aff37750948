#pragma once
// Display-capture collection: show a scene on a monitor in front of the FlatCam, let it settle,
// capture, write. Used for FlatNet-layout datasets (photographs) and for calibration pattern sets.
// Resumable: an item whose measurement PNG exists is done (it is written last, atomically), so an
// interrupted run continues where it stopped; nothing is captured twice and nothing is lost.
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

#include "hw/camera_device.hpp"
#include "hw/display.hpp"

namespace flatnet {

struct CollectOptions {
  int average = 1;      // frames averaged per capture
  int settle_ms = 500;  // wait after showing a scene (display response, auto-brightness)
  int64_t limit = 0;    // > 0: stop after this many new captures (a partial run; resumable)
  bool progress = true;
};

struct CollectReport {
  int64_t total = 0, captured = 0, skipped = 0;
  double seconds = 0;
  bool stopped = false;  // interrupted (Ctrl-C, Esc/q in the window) or limit reached before the end
};

struct CollectItem {
  std::string name;                      // output file name (NAME.png)
  std::function<torch::Tensor()> scene;  // what the display shows: {3,N,N} or {N,N} in [0,1]
};

// The shared loop. `meas_path(name)`: where the capture goes; `before_write(name, scene)`: writes
// anything that must exist before the capture counts as done (e.g. the ground truth).
CollectReport collect(const std::vector<CollectItem>& items, FrameSource& source, Display& display,
                      const CollectOptions& options,
                      const std::function<std::filesystem::path(const std::string&)>& meas_path,
                      const std::function<void(const std::string&, const torch::Tensor&)>& before_write = {});

struct DatasetCollectOptions {
  std::filesystem::path out;  // meas/, gt/, train_*.txt, val_*.txt (as `flatnet simulate`)
  int64_t scene_size = 256;   // ground truth and displayed scene side
  double val_fraction = 0.1;
  uint64_t seed = 0;
  CollectOptions collect;
};

// Photographs -> FlatNet-layout dataset of real captures. The lists name only complete pairs,
// with the same split rule as `flatnet simulate`, so a partial dataset is already trainable.
CollectReport collect_dataset(const std::vector<std::filesystem::path>& images, FrameSource& source, Display& display,
                              const DatasetCollectOptions& options);

}  // namespace flatnet
