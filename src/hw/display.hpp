#pragma once
// Showing scenes to a FlatCam (display-capture datasets, calibration patterns) and showing
// reconstructions (live view), through OpenCV highgui; or nowhere ("none") for headless runs.
#include <memory>
#include <string>

#include <torch/torch.h>

namespace flatnet {

struct DisplayOptions {
  std::string kind = "window";  // window | none
  std::string title = "flatnet";
  int x = 0, y = 0;        // window origin: the chosen monitor's top-left in the desktop (xrandr)
  bool fullscreen = true;  // scenes: full screen on that monitor, black around the image
  int scale = 0;           // integer magnification (nearest); 0 = the largest that fits the window
};

class Display {
 public:
  virtual ~Display() = default;
  // Shows {3,H,W} (or {H,W}) values in [0,1] (display codes / 255), with optional text drawn on top.
  virtual void show(const torch::Tensor& image, const std::string& text = "") = 0;
  // Lets the window system run for `ms` (>= 1); true when the user pressed Esc or q.
  virtual bool wait(int ms) = 0;
  virtual int64_t shown() const = 0;
};

// A window (errors clearly when there is no display server) or the headless stand-in.
std::unique_ptr<Display> make_display(const DisplayOptions& options);

// {3,H,W} (or {H,W}) in [0,1] -> the {Hc,Wc,3} uint8 BGR canvas shown: the image magnified by an
// integer factor with nearest-neighbour (a scene pixel stays a block of display pixels, as the
// calibration patterns assume), centred on black. scale 0: the largest factor that fits.
torch::Tensor compose_canvas(const torch::Tensor& image, int64_t canvas_h, int64_t canvas_w, int scale);

}  // namespace flatnet
