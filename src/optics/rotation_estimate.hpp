#pragma once
// The mask's rotation on the sensor that a camera file does not state, estimated from the
// display-capture pairs (issue 55 #4: instead of a loop over angles by hand).
//
// The geometry rotates each raw Bayer plane by `rotation` about its origin before the crop
// (io/raw.hpp rotate_planes): window W_t(r, c) = raw(sin t c' + cos t r', cos t c' - sin t r'),
// r' = r + crop top, c' = c + crop left. A small change d of the angle moves the window by
//   W_{t+d} ~ W_t + d G,        G = c' dW/dr - r' dW/dc                                        (1)
// and the capture the calibration model (optics/calibrate_dataset.hpp, eq. 2) fits is the centred
// window. At the mask's true angle t* the window is separable; at t it is that plus (t - t*) G, of
// which the separable fit absorbs a part. The residual R = Y - model therefore holds k (t - t*) G
// with 0 < k <= 1, and the projection
//   d(t) = <R, G> / <G, G>                                                                      (2)
// is zero at the true angle and rises through it with slope k. G is built from the model's
// prediction and the window's row and column means (averages of hundreds of pixels), never from the
// captures' pixels (the captures' own gradients find the root 0.5 mrad off on a noisy bench, the
// model's within 0.05): their noise stays out of G, so (2) carries no noise bias, whereas a residual
// energy compared across angles does (the bilinear rotation smooths the noise by an amount that
// depends on the angle, which dwarfs the rotation's signal on a noisy camera).
// The search (estimate_rotation) refits the calibration at each angle it tries and steps by the
// secant of d through the angles tried.
#include <cstdint>
#include <functional>
#include <vector>

#include <torch/torch.h>

#include "io/camera_config.hpp"
#include "optics/calibrate_dataset.hpp"

namespace flatnet {

struct WindowPair {
  torch::Tensor window;  // {4,rows,cols} the raw window at the angle tried, before centring (full scale)
  torch::Tensor scene;   // {4,N,N} the scene shown, linear light, per Bayer channel (unmixed)
  torch::Tensor valid;   // {rows,cols}: 1 where the rotation read the window from inside the plane
                         // (window_inside_plane), 0 where it filled in zeros; undefined: all inside
};

// Which pixels of the window at the geometry's angle are read from inside planes of {height,width}.
torch::Tensor window_inside_plane(int64_t height, int64_t width, const RawGeometry& g);

// d(t) of (2) over the pairs, for a calibration fitted to the same pairs at the same angle.
// `origin` is the window's top-left pixel in the plane (the crop's top and left).
double rotation_residual_projection(int64_t count, const std::function<WindowPair(int64_t)>& load,
                                    const DatasetCalibration& fit, const std::array<int64_t, 2>& origin);

struct RotationSearchOptions {
  double start = 0;                   // the angle the camera file states (radians)
  double limit = 0.02;                // how far from the start the angle is searched (radians)
  double bound = kMaxCameraRotation;  // and never beyond +-bound (the largest a camera file may state)
  double first_step = 2e-3;           // the first step, towards the root (radians)
  double tolerance = 5e-5;            // stop when a step is below this (radians)
  int fits = 5;                       // calibrations fitted at most (each one angle)
};

struct RotationSearch {
  double angle = 0;  // the estimate (radians)
  struct Probe {
    double angle, projection;
  };
  std::vector<Probe> probes;  // each angle tried with its d(t), in order
  bool converged = false;     // the last step was below the tolerance
  bool slope_found = true;    // false: d did not rise with the angle (no rotation signal above the noise)
};

// `project(angle)` fits the calibration at that angle and returns d(angle). Steps: the first of
// `first_step` against d's sign, then by the secant through the last two probes; a secant whose slope
// is not positive (noise, or no rotation signal) stops the search at the probe with the smallest |d|.
RotationSearch search_rotation(const std::function<double(double)>& project, const RotationSearchOptions& options);

}  // namespace flatnet
