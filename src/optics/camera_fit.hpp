#pragma once
// Does a capture come from this camera? A model or a calibration is only good for captures of the
// camera it describes; captures of another camera give images with no trace of the scene, silently.
//
// The physics: every capture of the camera is, after double-centring, Y = P X Q^T + s a b^T + E
// (optics/calibrate_dataset.hpp, eq. 1). P X Q^T lies in the span of U (P's column space) and V
// (Q's): the N^2-dimensional space {U C V^T}. So the part of Y outside that space, after its one
// strongest rank-1 component (the open part's light) is set aside, is the sensor's noise E alone,
// whose energy the camera's own noise model predicts from the light each pixel read:
//   var(pixel) = noise_gain * (v - dark) + noise_floor        (io/camera_config.hpp)
//   E||R||^2  ~= sum(var) * dof / (h w) - mean(var) (sqrt(h-1) + sqrt(w-1))^2,
// dof = (h-1)(w-1) - N^2 (the centred planes lose a row and a column of freedom; the last term is
// the noise a rank-1 fit takes along). fit = ||R||^2 / E||R||^2: 1 for this camera's captures, up
// to chance (its standard deviation is sqrt(2 / dof) over the four channels) and calibration error;
// above 1 when the light was coded by another mask, which puts most of its energy outside the span.
// A plain energy ratio cannot tell: noisy captures of the right camera keep only 0.3-0.5 of their
// energy in the span, since the noise fills every dimension.
//
// A second test catches a near twin: another mask on the same sensor whose shadow moves by the same
// shift per scene pixel. Its factors span nearly the same space, so the energy it leaves outside is
// only a few percent above the noise's (fit 1.004-1.06): pooled over 10^5 dimensions, it hides. But
// that energy is structured: the twin's leak (I - U U^T) P' X Q'^T V is a coded scene, a few strong
// singular directions, where noise spreads its energy evenly over all of them (Marchenko-Pastur). So:
// in the two blocks where the leak is first order, B = U^T Y (I - V V^T) {N,w} and
// C = (I - U U^T) Y V {h,N}, each plane's strongest rank-1 component (the open part's light) set
// aside, the four planes stacked (the same scene in each), the leak is the largest singular value
// over the 41st (coded_leak). Noise gives a value its shape alone fixes (1.17-1.20 at 500x620, N 256),
// whatever the light level and without the noise model; a twin's coded scene gives 1.3-3.
#include <string>
#include <vector>

#include <torch/torch.h>

#include "io/camera_config.hpp"
#include "optics/camera.hpp"

namespace flatnet {

struct CameraFitResult {
  double fit = 0;            // unexplained energy over what the noise model predicts (1: a perfect fit)
  bool matches = false;      // fit <= the threshold
  double saturated = 0;      // share of the window's pixels at full scale (their noise is clipped)
  bool judged = true;        // false when over 1 % of the pixels are saturated: matches is then true
  double leak = 0;           // coded structure outside the calibration's spans (coded_leak; noise alone: ~1.2)
  bool leak_matches = true;  // leak <= its threshold (part of matches)
};

// What a user does about captures that do not fit: one sentence, shared by infer, recon and live.
inline const char* misfit_advice() {
  return "they were taken with another camera, and their reconstructions show no scene. Calibrate your camera "
         "(flatnet calibrate --dataset) and adapt the model to it (flatnet train --init-from MODEL --reinit "
         "inversion); docs/own-camera.md";
}

// The statistic's two halves, shared with calibrate --dataset (which fits the noise model on them, so
// that the camera fit and the noise model it tests against measure the same thing):
// each plane's energy outside span(U) x span(V), its strongest rank-1 component set aside
// (Y {4,h,w}; U {4,h,N}, V {4,w,N} orthonormal) -> {4} float64;
torch::Tensor unexplained_energy(const torch::Tensor& Y, const torch::Tensor& U, const torch::Tensor& V);
// and the share of a pixel's noise variance expected there: dof / (h w), less what the rank-1
// component takes, (sqrt(h-1) + sqrt(w-1))^2 / (h w), dof = (h-1)(w-1) - N^2.
double outside_share(int64_t h, int64_t w, int64_t n);
// A window's pixels at the ADC's top code as stored, (2^bits - 1) * 2^(16 - bits) / 65535 of full
// scale (0.99902 at 10 bits): {4,h,w} -> bool, same shape. Clipped pixels carry no noise and are no
// P X Q^T, so over kMaxSaturatedShare of them a capture is not judged, and calibrate --dataset leaves
// such pairs out of the leak threshold.
torch::Tensor at_full_scale(const torch::Tensor& window, int adc_bits);
constexpr double kMaxSaturatedShare = 0.01;
// The near-twin test (header comment): the larger, over the blocks B and C, of the stacked planes'
// largest singular value over their 41st. Y {4,h,w} (double-centred here, whatever its centring);
// U {4,h,N}, V {4,w,N} orthonormal. Needs N > 41 and h, w > N + 41.
double coded_leak(const torch::Tensor& Y, const torch::Tensor& U, const torch::Tensor& V);
// What noise alone gives for this geometry: the largest coded_leak of `draws` Gaussian captures
// (fixed seed; the statistic does not depend on the noise's level).
double noise_leak(const torch::Tensor& U, const torch::Tensor& V, int draws = 3);

// The camera's noise model as the camera fit will test captures against it, measured on captures of
// the camera itself: each plane's energy outside the calibration's span (unexplained_energy), per
// pixel and per share of a pixel's noise expected there, against the plane's light level
// (gain * (mean v - dark) + floor summed over the pixels v is a line in the level); least squares,
// then dark, floor >= 0. What an estimated calibration leaves outside its span varies from scene to
// scene, so the captures' own fits set the camera fit's threshold: their largest with a margin, or
// their mean plus five deviations if larger; the same for the near-twin statistic (coded_leak).
struct NoiseSample {
  torch::Tensor meas;    // {4,h,w} double-centred capture planes, no level (without_level)
  torch::Tensor level;   // {4} the window's mean raw value per plane, full scale
  double saturated = 0;  // share of the window's pixels at full scale (at_full_scale)
};
struct NoiseModelFit {
  bool found = false;                                // false: fewer than 2 captures, or no line with a positive gain
  double noise_gain = 0, noise_floor = 0, dark = 0;  // CameraConfig's keys
  double fit_threshold = 0;                          // 0 when not found
  double leak_threshold = 0;                         // 0 when no capture could be tested (all saturated)
  std::vector<double> fits;                          // each capture's fit under the fitted model
};
// P {4,h,N}, Q {4,w,N}: the calibration (any column scaling; only the spans matter).
NoiseModelFit fit_noise_model(const std::vector<NoiseSample>& samples, const torch::Tensor& P, const torch::Tensor& Q);

// Whether the camera fit can test captures of this geometry at all: the window's (h-1)(w-1) degrees
// of freedom outside an N x N scene's span must be many (over 1000), or the statistic is chance alone.
// A window no larger than the scene leaves none; such a camera is reconstructed without a fit.
bool camera_fit_measurable(int64_t h, int64_t w, int64_t n);

class CameraFit {
 public:
  // Errors name the camera when it has no noise model (noise_gain: run `flatnet calibrate --dataset`
  // or write the sensor's values into its .yaml) or the calibration does not match its geometry.
  CameraFit(const Calibration& calib, const CameraConfig& camera);
  // raw_unit: the whole raw frame, {H,W}, full scale [0,1] (io/raw.hpp load_raw_unit).
  CameraFitResult measure(const torch::Tensor& raw_unit) const;
  double threshold() const { return threshold_; }
  double leak_threshold() const { return leak_threshold_; }
  // How far a capture is from fitting: the larger of fit and leak over their thresholds (> 1: a misfit).
  double excess(const CameraFitResult& r) const;
  // Why a capture does not fit, for messages: "fit 4.2 against <= 1.02", "coded leak 1.8 against <= 1.31 ...", or both.
  std::string verdict(const CameraFitResult& r) const;
  const std::string& camera_name() const { return camera_.name; }

 private:
  torch::Tensor U_, V_;        // {4,h,N}, {4,w,N} orthonormal, float32
  torch::Tensor fixed_light_;  // {4,h,w} float32: the calibration's fixed light, subtracted first; or undefined
  CameraConfig camera_;
  double threshold_ = 0;
  double leak_threshold_ = 0;  // noise_leak x 1.1, or the camera file's when larger (an estimated calibration)
  double outside_share_ = 0;   // outside_share(h, w, N)
};

// Captures of one batch (the files of one `infer`, the frames of one `live` view) come from one
// camera, and a batch is judged as a whole too. A near twin's captures leak 1.2-3.2 by their scenes,
// and a few (flat, dim scenes with little coded structure beside the noise) fall inside noise's reach
// one by one; their batch does not: its median capture leaks 1.86, the camera's own median 1.20
// (docs/own-camera.md, 150 captures each). So when at least kMinBatchJudged captures are judged and
// the lower median of their excess (CameraFit::excess) is above 1, every capture of the batch is
// flagged, judged or not. The median keeps a batch of the camera's own captures with a few odd ones
// (a covered lens, a flash) from being flagged as a whole: those stay flagged alone.
constexpr int64_t kMinBatchJudged = 3;
struct BatchFit {
  int64_t judged = 0;        // captures the camera fit judged
  double median_excess = 0;  // the lower median of their excess (0 when none is judged)
  bool foreign = false;      // judged >= kMinBatchJudged and median_excess > 1
};
BatchFit judge_batch(const CameraFit& fit, const std::vector<CameraFitResult>& results);

}  // namespace flatnet
