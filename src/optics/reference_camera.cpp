#include "optics/reference_camera.hpp"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <iomanip>
#include <sstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "optics/camera.hpp"
#include "optics/separable_inverse.hpp"

namespace flatnet {

namespace {

void require_valid(const ReferenceCameraOptions& o, const std::optional<WhiteCaptureInput>& white) {
  require(std::isfinite(o.lambda) && o.lambda > 0 && o.lambda < 1, "--reference-lambda",
          "a relative regulariser in (0, 1), such as 3e-4");
  require(o.fit.shift.min_shift >= kSmallestShiftSearched && o.fit.shift.max_shift > o.fit.shift.min_shift &&
              o.fit.shift.max_shift <= kLargestShiftSearched,
          "--min-shift",
          "0.05 <= --min-shift < --max-shift <= 16 sensor pixels per scene pixel (a smaller shift is not a "
          "FlatCam's shadow, and the search's cost grows with the range's ratio)");
  if (!white) return;
  require(std::isfinite(white->light) && white->light > 0 && white->light <= 1e3, "--white-light",
          "the white capture's light, relative to the display's white (1), within (0, 1000]");
  require(white->sample.saturated <= kWhiteSaturatedAtMost, white->name,
          "is saturated (" + std::to_string(100 * white->sample.saturated) +
              " % of its window at full scale): take it at a shorter exposure or a dimmer white, and give its "
              "light with --white-light");
}

// Step 2: the leave-one-out check against the whole calibration.
void check_held_out(const std::vector<ReferencePair>& pairs, const ReferenceCameraOptions& o, ReferenceCamera& cam) {
  if (pairs.size() < 3) return;
  cam.held = leave_one_out(pairs, o.lambda, o.fit, &cam.fit.calib);
  double sum = 0, squared_change = 0;
  for (const auto& h : cam.held) {
    cam.held_leak = std::max(cam.held_leak, h.leak);
    sum += (h.correlation[0] + h.correlation[1] + h.correlation[2] + h.correlation[3]) / 4;
    squared_change += h.change_coded * h.change_coded;
  }
  const auto n = static_cast<double>(cam.held.size());
  cam.held_mean = sum / n;
  // A fit from n - 1 pairs moves by 1 / (n (n - 1)) of a pair's variance from the whole fit, the whole
  // fit by 1 / n from the truth, so its uncertainty is sqrt(n - 1) times the rms move.
  cam.held_change = std::sqrt((n - 1) * squared_change / n);
  // A calibration that cannot reconstruct a pair it did not see has fitted the pairs, not the camera.
  require(cam.held_mean >= 0.5, "calibrate",
          "held-out pairs are not reconstructed (mean correlation " + std::to_string(cam.held_mean) +
              "): the references are not reconstructions of these captures, the colour order is wrong "
              "(--reference-order), or the shifts lie outside --min-shift..--max-shift");
}

// Step 3 with a white capture (eq. 2): refused, naming the file, when it shows no uniform scene.
LightUnit white_light_unit(const WhiteCaptureInput& white, double lambda, ReferenceCalibration& fit) {
  const auto frame = fit_white_frame(white.sample.meas, fit.calib, lambda);
  LightUnit unit;
  unit.source = LightUnitSource::white_capture;
  unit.light = white.light;
  unit.white_name = white.name;
  unit.white_residual = (frame.residual[0] + frame.residual[1] + frame.residual[2] + frame.residual[3]) / 4;
  require(unit.white_residual <= kWhiteResidualAtMost, white.name,
          "is not a uniform scene: a uniform scene leaves " + std::to_string(unit.white_residual) +
              " of its well-measured coded light unexplained (at most " + std::to_string(kWhiteResidualAtMost) +
              "); the white must fill the camera's view");
  for (size_t c = 0; c < 4; ++c) {
    require(std::isfinite(frame.level[c]) && frame.level[c] > 0, white.name,
            std::string("shows no white scene's shadow in channel ") + kChannelNames[c] +
                " (a dark frame, or another camera's?)");
    unit.level[c] = frame.level[c];
    unit.scale[c] = white.light / frame.level[c];
  }
  rescale_scene_units(fit, unit.scale);
  return unit;
}

// Step 3 without one: a capture at twice the exposure of a scene is a capture of a scene twice as
// bright, and a min-max stretched reference says nothing of either, so the prior typical_scene_scale
// sets the unit (one scale: the colour kept).
LightUnit prior_light_unit(double scene_light, ReferenceCalibration& fit) {
  LightUnit unit;
  if (scene_light <= 0) return unit;
  const double scale = typical_scene_scale(fit, scene_light);
  if (scale <= 0) {
    unit.no_scene_light = true;
    return unit;
  }
  unit.source = LightUnitSource::scene_prior;
  unit.light = scene_light;
  unit.scale = {scale, scale, scale, scale};
  rescale_scene_units(fit, unit.scale);
  return unit;
}

// Steps 4 and 5.
void identify_camera_keys(const std::vector<NoiseSample>& samples, ReferenceCamera& cam) {
  auto& known = cam.camera;
  known.tikhonov_lambda =
      absolute_tikhonov_lambda(separable_inverse(cam.fit.calib.P, cam.fit.calib.Q, 1.0), cam.lambda);
  // The noise model from what the captures hold beyond the calibration: less its fixed light too.
  auto beyond = samples;
  for (auto& sample : beyond) sample.meas = without_fixed_light(sample.meas, cam.fit.calib.fixed_light);
  cam.noise = fit_noise_model(beyond, cam.fit.calib.P, cam.fit.calib.Q);
  if (!cam.noise.found) return;
  known.noise_gain = cam.noise.noise_gain;
  known.noise_floor = cam.noise.noise_floor;
  known.dark = cam.noise.dark;
  known.fit_threshold = cam.noise.fit_threshold;
  known.leak_threshold = cam.noise.leak_threshold;
  // A few captures' calibration misses structured light, and a capture it did not see leaks more than
  // the captures it was fitted to: the held-out captures' leaks set the threshold too.
  if (cam.held_leak > 0 && cam.noise.leak_threshold > 0)
    known.leak_threshold = std::max(cam.noise.leak_threshold, std::min(1e3, 1.1 * cam.held_leak));
  std::vector<torch::Tensor> levels;
  for (const auto& sample : samples) levels.push_back(sample.level);
  known.open_light = open_light_of(levels, cam.fit, cam.noise.dark);
}

double fixed_light_share(const Calibration& calib, const std::vector<NoiseSample>& samples) {
  if (!calib.fixed_light.defined()) return -1;
  double captures = 0;
  for (const auto& sample : samples) captures += sample.meas.to(torch::kFloat64).norm().item<double>();
  captures /= static_cast<double>(samples.size());
  return calib.fixed_light.norm().item<double>() / std::max(1e-300, captures);
}

}  // namespace

ReferenceCamera identify_reference_camera(const std::vector<ReferencePair>& pairs,
                                          const std::vector<NoiseSample>& samples,
                                          const std::optional<WhiteCaptureInput>& white, const CameraConfig& geometry,
                                          const ReferenceCameraOptions& o) {
  require_valid(o, white);
  require(samples.size() == pairs.size(), "calibrate",
          "needs one capture sample per pair (" + std::to_string(samples.size()) + " for " +
              std::to_string(pairs.size()) + " pairs)");
  ReferenceCamera cam;
  cam.lambda = o.lambda;
  cam.captures = pairs.size();
  cam.camera = geometry;
  // The whole calibration first: the held-out fits are measured against it as well.
  cam.fit = calibrate_from_references(pairs, o.fit);
  check_held_out(pairs, o, cam);
  cam.light = white ? white_light_unit(*white, o.lambda, cam.fit) : prior_light_unit(o.scene_light, cam.fit);
  identify_camera_keys(samples, cam);
  cam.fixed_light_share = fixed_light_share(cam.fit.calib, samples);
  return cam;
}

std::string reference_camera_header(const ReferenceCamera& cam) {
  const auto& fit = cam.fit;
  std::ostringstream head;
  head << "# identified by `flatnet calibrate --references` from " << cam.captures
       << " captures and reconstructions of them; the shadow moves " << std::setprecision(6) << fit.shift_rows
       << " sensor pixels per scene row, " << fit.shift_cols << " per scene column; residual per channel:";
  for (const double v : fit.residual) head << " " << std::setprecision(4) << v;
  if (cam.fixed_light_share >= 0)
    head << "\n# a fixed light every capture holds whatever the scene (flare, stray light) was fitted as its own term, "
         << std::setprecision(3) << cam.fixed_light_share
         << " of a capture's norm: calib.mat's fixed_light_*, subtracted before inversion (--fixed-light)";
  if (fit.kernels_rows.defined()) head << "\n# " << describe_shared_mask(fit);
  if (cam.held_mean >= 0)
    head << "\n# leave-one-out: mean held-out correlation " << std::setprecision(4) << cam.held_mean;
  if (cam.held_change >= 0)
    head << "; its coded light is uncertain by " << std::setprecision(3) << cam.held_change
         << " of itself (the jackknife of the pairs' coded light: sqrt(n - 1) x the rms distance of a calibration "
            "without one pair from this one, on that pair's scene): train with data.calibration_error of that size";
  const auto& unit = cam.light;
  if (unit.source == LightUnitSource::white_capture)
    head << "\n# scene light from the white capture "
         << printable(std::filesystem::path(unit.white_name).filename().string()) << " (light " << unit.light
         << "); without it the references' units";
  else if (unit.source == LightUnitSource::scene_prior)
    head << "\n# scene light not measured: the pairs' scenes taken to hold " << unit.light
         << " of the display's white on average (--scene-light), the references' units x " << unit.scale[0]
         << "; a white capture measures it (--white-capture)";
  head << "\n# tikhonov_lambda is " << cam.lambda << " of the largest squared singular value product\n";
  return head.str();
}

}  // namespace flatnet
