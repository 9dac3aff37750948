#pragma once
// The closed-form Tikhonov inverse of the separable model Y_c = P_c X_c Q_c^T, per channel c
// (FlatNet thesis eq. 2.6), computed once from the SVDs P = U_L S_L V_L^T, Q = U_R S_R V_R^T:
//   X = V_L [ (s_L s_R^T) / ((s_L s_R^T)^2 + lambda) o (U_L^T Y U_R) ] V_R^T.
// One implementation for recon's Tikhonov and the naive model's first stage (nn TikhonovLayer).
#include <torch/torch.h>

namespace flatnet {

struct SeparableInverse {
  torch::Tensor ULt, UR, VL, VRt;  // {4,N,h}, {4,w,N}, {4,N,N}, {4,N,N} float32
  torch::Tensor sL, sR;            // {4,N} float64 singular values
  torch::Tensor filter;            // {4,N,N} float32: s / (s^2 + lambda), s = s_L s_R^T
};

// P {4,h,N}, Q {4,w,N}: thin SVDs in float64, stored in float32 for fast products.
SeparableInverse separable_inverse(const torch::Tensor& P, const torch::Tensor& Q, double lambda);
// The filter of eq. 2.6 for another lambda (the SVDs unchanged).
torch::Tensor tikhonov_filter(const torch::Tensor& sL, const torch::Tensor& sR, double lambda);
// The singular pairs the camera measures above its regulariser, s_Li s_Rj >= sqrt(lambda): {4,N,N}
// float64, 1 on them and 0 elsewhere (where the sensor's noise is most of what a capture holds).
torch::Tensor well_measured_pairs(const torch::Tensor& sL, const torch::Tensor& sR, double lambda);
// Y {B,4,h,w} -> X {B,4,N,N}, in the order (U_L^T Y) U_R, then V_L (Z o filter) V_R^T.
torch::Tensor apply_separable_inverse(const torch::Tensor& ULt, const torch::Tensor& UR, const torch::Tensor& VL,
                                      const torch::Tensor& VRt, const torch::Tensor& filter, const torch::Tensor& Y);

}  // namespace flatnet
