#pragma once
// A simulated display-capture bench's errors (io/camera_config.hpp BenchErrors), applied where they
// arise along the capture chain of simulate_raw_linear (optics/camera.hpp):
//   display:  the photograph shown off-centre and scaled; each capture's exposure flickers
//   colour:   each Bayer plane sees a mix of the display's three primaries (cross-talk)
//   optics:   a second, weaker separable term; the mask rotated on the sensor; stray light; a
//             calibration that errs, redrawn per capture
//   sensor:   hot pixels stuck bright at fixed places
// With no errors (BenchErrors{}) every step returns its input.
#include <torch/torch.h>

#include "io/camera_config.hpp"

namespace flatnet {

struct Rig;

// What the display shows of a linear scene {3,N,N}: shifted by display_shift scene pixels (down and
// right) and scaled by display_scale about its centre (bilinear; black outside), times a flicker
// factor exp(flicker * z), z ~ N(0, 1) drawn from `gen`.
torch::Tensor bench_display(const BenchErrors& bench, const torch::Tensor& scene_linear,
                            c10::optional<at::Generator> gen);

// Cross-talk: each primary's plane {3,N,N} carries (1 - c) of its own light and c / 2 of each other's.
torch::Tensor bench_crosstalk(const BenchErrors& bench, const torch::Tensor& rgb);

// The expected signal {1,4,h,w} of scene planes {1,4,N,N} with the optics' errors: a second term
// second_term * gain * PhiL' X PhiR'^T (PhiL, PhiR shifted by 9 and -7 sensor pixels: a ghost of
// the mask), the whole response rotated by mask_rotation about the plane's centre, and stray light
// rising linearly to stray_light at the bottom-right corner.
torch::Tensor bench_signal(const BenchErrors& bench, const Rig& rig, const torch::Tensor& planes,
                           const torch::Tensor& signal);

// The signal {1,4,h,w} of scene planes {1,4,N,N} through a calibration that errs, redrawn for every
// capture (from `gen`): the change that iid Gaussian entries added to both factors make in the coded
// light P X Q^T, scaled per channel to calibration_error of that light's norm, added.
torch::Tensor bench_calibration(const BenchErrors& bench, const Rig& rig, const torch::Tensor& planes,
                                const torch::Tensor& signal, c10::optional<at::Generator> gen);

// Hot pixels on a stored raw frame {2h,2w} int32: hot_pixels places fixed by the frame's size, each
// stuck at 40-100 % of full scale (whole ADC steps of an adc_bits sensor).
torch::Tensor bench_hot_pixels(const BenchErrors& bench, const torch::Tensor& raw, int adc_bits);

}  // namespace flatnet
