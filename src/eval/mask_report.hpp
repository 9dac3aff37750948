#pragma once
// `flatnet mask report`: masks compared as a mask designer needs them compared.
//  1. The thesis's protocol (Wiener deconvolution of a circular-convolution capture): learned
//     rank-k masks against MLS and FlatNet's 02 mask, with a noise sweep.
//  2. The real, separable FlatCam: each candidate code pair built into the reference camera
//     (optics/separable_camera), the held-out photographs captured through its rig exactly as
//     `flatnet simulate --seed 1 --only val` captures them (Poisson and read noise, 10-bit ADC),
//     reconstructed from a calibration with 3 % error by Tikhonov (lambda tuned per camera and light
//     on the first held-out photographs) and, where one was trained on that camera, by FlatNet;
//     then a light sweep (fewer photons per full scale: more shot noise, the same scenes).
#include <filesystem>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "io/camera_config.hpp"
#include "optics/separable_camera.hpp"

namespace flatnet {

// A FlatNet trained on one candidate's camera: planes {B,4,h,w} preprocessed with `geometry` ->
// sRGB images {B,3,N,N} in [0,1].
struct CameraModel {
  std::function<torch::Tensor(const torch::Tensor&)> forward;
  RawGeometry geometry;
  std::string label;  // e.g. the model file's name
};

struct SeparableCandidate {
  std::string name;  // row label
  CodePair codes;
  std::string origin;  // one line: where the codes come from
  std::optional<CameraModel> flatnet;
};

struct SeparableReportOptions {
  RawGeometry geometry;           // the reference camera's preprocessing (crop); Tikhonov reads centred planes
  SeparableCameraOptions camera;  // the construction (sensor, blur, gains, full well)
  double calib_error = 0.03;      // as `flatnet mask camera` and the shipped calib.mat
  uint64_t calib_seed = 0;
  uint64_t noise_seed = 1;  // the noise of `flatnet simulate --seed 1`
  std::vector<double> lambdas = {1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2};
  std::vector<double> light = {1.0, 0.25, 1.0 / 16, 1.0 / 64};  // photons per full scale, relative to the camera's
  int64_t tune_count = 50;  // held-out photographs that choose lambda; the rest are scored
  int64_t count = 0;        // > 0: score at most this many after those
  bool progress = true;
};

struct SeparableScore {
  std::string name, origin, flatnet_label;
  double throughput = 0;
  double cond_p = 0, cond_q = 0;                  // of the gb channel's calibration matrices
  double low_share_rows = 0, low_share_cols = 0;  // share of each code's AC power in the lowest eighth of frequencies
  std::vector<double> lambda_sweep_psnr;          // at full light, every held-out photograph, per options.lambdas
  std::vector<double> lambda, psnr, ssim;         // per light level: tuned lambda, scored PSNR / SSIM
  double flatnet_psnr = std::nan(""), flatnet_ssim = std::nan("");  // at full light, the scored photographs
  int64_t scored = 0;                                               // photographs scored (after the tuning ones)
};

// Scores every candidate on the held-out photographs (split_image_files(images, 0.1, 1).second).
std::vector<SeparableScore> score_separable_cameras(const std::vector<SeparableCandidate>& candidates,
                                                    const std::vector<std::filesystem::path>& held_out,
                                                    const SeparableReportOptions& options);

// The report's section: the table at the camera's light, the lambda sweep, the light sweep and the
// code analysis, in Markdown.
std::string separable_section(const std::vector<SeparableScore>& scores, const SeparableReportOptions& options);

// The Wiener rank-1 masks' vectors mapped to separable codes: sign(U), sign(V) (vectors.mat), with
// the share of mask elements where (1 + sign(u) sign(v)^T) / 2 agrees with the learned mask.
struct MappedCodes {
  CodePair codes;
  double agreement = 0;
};
MappedCodes codes_from_wiener_mask(const std::filesystem::path& mask_dir);

struct MaskReportOptions {
  bool wiener = true;                            // the Wiener-protocol sections (1.)
  std::vector<std::filesystem::path> mask_dirs;  // folders written by `flatnet mask train`
  std::filesystem::path images;                  // photographs; the held-out split is used
  std::filesystem::path out;                     // report.md, masks.png, sweep.png, separable_sweep.png
  double noise = 3e-4;                           // Wiener protocol: noise sigma of the main table
  int64_t tune_count = 50, count = 0;            // Wiener protocol: photographs tuning gamma, scored after them
  std::vector<SeparableCandidate> separable;     // empty: no separable section
  SeparableReportOptions separable_options;
};

// Writes OUT/report.md and its figures; returns the Markdown.
std::string write_mask_report(const MaskReportOptions& options);

}  // namespace flatnet
