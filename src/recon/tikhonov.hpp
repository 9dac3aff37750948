#pragma once
// Classical FlatCam reconstructions on the separable model Y_c = P_c X_c Q_c^T + E.
#include <torch/torch.h>

#include "optics/camera.hpp"

namespace flatnet {

// Tikhonov-regularised least squares, closed form via the SVDs (FlatNet thesis eq. 2.6):
//   P = U_L S_L V_L^T, Q = U_R S_R V_R^T,
//   X = V_L [ (s_L s_R^T) / ((s_L s_R^T)^2 + lambda) o (U_L^T Y U_R) ] V_R^T.
// The SVDs and the filter are computed once, in the constructor.
class Tikhonov {
 public:
  Tikhonov(const Calibration& calib, double lambda);
  // {B,4,h,w} measurement planes -> {B,4,N,N} linear-light scene planes.
  torch::Tensor operator()(const torch::Tensor& Y) const;
  double lambda() const { return lambda_; }
  void set_lambda(double lambda);

 private:
  double lambda_;
  torch::Tensor ULt_, UR_, VL_, VRt_;  // {4,N,h}, {4,w,N}, {4,N,N}, {4,N,N} float32
  torch::Tensor sL_, sR_;              // {4,N}
  torch::Tensor filter_;               // {4,N,N}
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
