#pragma once
// What the camera measures, taken from the measurement (issue 90): a network's picture corrected by
// the capture on the part of the scene the calibration resolves well.
//
// Per Bayer channel c the centred capture is Y_c = P_c X_c Q_c^T + E (the light level removed, as
// Tikhonov sees it). With P = U_L S_L V_L^T and Q = U_R S_R V_R^T, the scene's coefficient
// (V_L^T X V_R)_ij reaches the capture multiplied by s_ij = s_Li s_Rj. The network's picture f(y)
// (sRGB) becomes linear-light planes X^ (through the camera's colour mix where it has one), and
//   X = X^ + V_L [ s / (s^2 + c^2 lambda) o U_L^T (Y / a - A X^) U_R ] V_R^T,                   (1)
// Tikhonov's own inverse (thesis eq. 2.6) applied to what the picture leaves unexplained, with the
// camera file's tikhonov_lambda (set for its noise) raised c^2 times: a pair the camera measures far
// above its noise (s_ij >> c sqrt(lambda)) is taken from the capture, a pair below it stays the
// network's. a is the capture's exposure against the picture's, one number per capture, fitted by
// least squares on the pairs with s_ij >= sqrt(lambda) (not per channel: a colour error is the
// measurement's to correct). The double-centred capture holds no row or column means, so (1) leaves
// the picture's own. An optional Gaussian on the correction keeps its coarse part alone (colour and
// shading), where noise through (1) would otherwise show as grain.
#include <memory>
#include <string>

#include <torch/torch.h>

#include "io/camera_config.hpp"
#include "optics/camera.hpp"
#include "optics/separable_inverse.hpp"
#include "recon/reconstructor.hpp"

namespace flatnet {

struct DataConsistencyOptions {
  double strength = 10;  // c of (1): the regulariser is c^2 tikhonov_lambda (10: see docs/evaluation.md)
  double blur = 0;       // sigma (scene pixels) of a Gaussian on the correction; 0: none
};

class DataConsistency {
 public:
  DataConsistency(const Calibration& calib, const CameraConfig& camera, DataConsistencyOptions options);
  // planes {B,4,h,w} as loaded (light level included), picture {B,3,N,N} sRGB -> {B,3,N,N} sRGB.
  torch::Tensor operator()(const torch::Tensor& planes, const torch::Tensor& picture) const;
  // The same, differentiable in the picture: the layer a model with model.consistency trains with.
  torch::Tensor correct(const torch::Tensor& planes, const torch::Tensor& picture) const;
  // The share of singular pairs the capture dominates in (1), s_ij >= c sqrt(lambda) (mean over channels).
  double measured_share() const { return measured_share_; }
  double strength() const { return strength_; }
  // How far a picture is from its capture on the pairs the camera measures above its noise
  // (s_ij >= sqrt(lambda)): sum (U_L^T Y U_R - a U_L^T A X^ U_R)^2 over those pairs, relative to the
  // capture's own energy there, one number per capture {B}, with a fitted as in (1) and held fixed.
  // Differentiable in the picture: the loss of test-time adaptation (recon/adaptation.hpp).
  torch::Tensor disagreement(const torch::Tensor& planes, const torch::Tensor& picture) const;

 private:
  // The capture's and the picture's coefficients on the calibration's singular pairs, and the
  // capture's exposure against the picture's (gain {B,1,1,1}; usable {B}: a finite positive fit).
  struct Coefficients {
    torch::Tensor capture, picture, gain, usable;  // {B,4,N,N}, {B,4,N,N}, {B,1,1,1}, {B}
  };
  Coefficients coefficients(const torch::Tensor& planes, const torch::Tensor& X) const;
  // The Gaussian {4,1,k,k} (k = 2 ceil(3 sigma) + 1) on the correction; refused when its reach does
  // not fit in a `scene`-pixel picture.
  static torch::Tensor correction_blur(double sigma, int64_t scene);
  torch::Tensor to_planes(const torch::Tensor& srgb) const;      // {B,3,N,N} sRGB -> {B,4,N,N} linear
  torch::Tensor from_planes(const torch::Tensor& planes) const;  // {B,4,N,N} linear -> {B,3,N,N} sRGB

  Centring centring_;
  torch::Tensor P_, Q_;       // {4,h,N}, {4,w,N} float32
  torch::Tensor mix_;         // {4,3} float32, or undefined (b = B, gb = gr = G, r = R)
  double display_gamma_ = 0;  // CameraConfig::display_gamma: the picture's values <-> light
  SeparableInverse svd_;      // the SVDs of P and Q
  torch::Tensor gain_pairs_;  // {4,N,N} float32: 1 where s_ij >= sqrt(lambda), the exposure's fit
  torch::Tensor filter_;      // {4,N,N} float32: s / (s^2 + c^2 lambda) of (1)
  torch::Tensor blur_;        // {4,1,k,k} float32 Gaussian, or undefined
  double measured_share_ = 0;
  double strength_;
};

// A reconstructor whose pictures are made consistent with their captures by (1).
std::unique_ptr<Reconstructor> with_data_consistency(std::unique_ptr<Reconstructor> engine, const Calibration& calib,
                                                     const CameraConfig& camera, DataConsistencyOptions options);
std::unique_ptr<Reconstructor> with_data_consistency(std::unique_ptr<Reconstructor> engine,
                                                     std::shared_ptr<const DataConsistency> step);

}  // namespace flatnet
