#pragma once
// Classical FlatCam reconstructions on the separable model Y_c = P_c X_c Q_c^T + E.
#include <torch/torch.h>

#include "optics/camera.hpp"
#include "optics/separable_inverse.hpp"

namespace flatnet {

// Tikhonov-regularised least squares, closed form via the SVDs (FlatNet thesis eq. 2.6; the
// algebra is optics/separable_inverse). The SVDs and the filter are computed once, in the constructor.
class Tikhonov {
 public:
  Tikhonov(const Calibration& calib, double lambda);
  // {B,4,h,w} measurement planes -> {B,4,N,N} linear-light scene planes.
  torch::Tensor operator()(const torch::Tensor& Y) const;
  double lambda() const { return lambda_; }
  void set_lambda(double lambda);

 private:
  double lambda_;
  SeparableInverse inverse_;
};

// Total-variation regularised reconstruction, per channel:
//   min_{X >= 0} 1/2 ||P X Q^T - Y||^2 + lambda TV(X)      (isotropic TV)
// solved with FISTA (Beck & Teboulle 2009); the TV proximal step is the fast gradient projection
// (FGP) on the dual with the non-negativity constraint. Starts from the Tikhonov solution.
struct TVOptions {
  double lambda = 1e-4;
  int iterations = 60;            // FISTA iterations
  int prox_iterations = 10;       // FGP iterations per proximal step
  double tikhonov_lambda = 3e-4;  // for the starting point
};

// Forward differences with Neumann boundary, {..,N,N} -> (d/dcol, d/drow), and the divergence,
// the negative adjoint: <tv_gradient(x), p> = -<x, tv_divergence(p)>.
std::pair<torch::Tensor, torch::Tensor> tv_gradient(const torch::Tensor& x);
torch::Tensor tv_divergence(const torch::Tensor& px, const torch::Tensor& py);

class TVSolver {
 public:
  TVSolver(const Calibration& calib, TVOptions options);
  torch::Tensor operator()(const torch::Tensor& Y) const;  // {B,4,h,w} -> {B,4,N,N}

 private:
  TVOptions opt_;
  torch::Tensor P_, Q_;  // {4,h,N}, {4,w,N} float32
  double lipschitz_;     // ||P||^2 ||Q||^2 (largest over channels)
  Tikhonov init_;
};

}  // namespace flatnet
