#include "optics/separable_inverse.hpp"

#include <cmath>

namespace flatnet {

SeparableInverse separable_inverse(const torch::Tensor& P, const torch::Tensor& Q, double lambda) {
  torch::NoGradGuard no_grad;
  auto [UL, sL, VLt] = torch::linalg_svd(P.to(torch::kFloat64), false);  // {4,h,N},{4,N},{4,N,N}
  auto [UR, sR, VRt] = torch::linalg_svd(Q.to(torch::kFloat64), false);
  SeparableInverse s;
  s.ULt = UL.transpose(1, 2).contiguous().to(torch::kFloat32);
  s.UR = UR.contiguous().to(torch::kFloat32);
  s.VL = VLt.transpose(1, 2).contiguous().to(torch::kFloat32);
  s.VRt = VRt.contiguous().to(torch::kFloat32);
  s.sL = sL;
  s.sR = sR;
  s.filter = tikhonov_filter(sL, sR, lambda);
  return s;
}

torch::Tensor well_measured_pairs(const torch::Tensor& sL, const torch::Tensor& sR, double lambda) {
  const auto s = sL.to(torch::kFloat64).unsqueeze(2) * sR.to(torch::kFloat64).unsqueeze(1);  // {4,N,N}
  return (s >= std::sqrt(lambda)).to(torch::kFloat64);
}

torch::Tensor tikhonov_filter(const torch::Tensor& sL, const torch::Tensor& sR, double lambda) {
  const auto s = sL.unsqueeze(2) * sR.unsqueeze(1);  // {4,N,N} products of singular values
  return (s / (s * s + lambda)).to(torch::kFloat32).contiguous();
}

torch::Tensor apply_separable_inverse(const torch::Tensor& ULt, const torch::Tensor& UR, const torch::Tensor& VL,
                                      const torch::Tensor& VRt, const torch::Tensor& filter, const torch::Tensor& Y) {
  const auto Z = torch::matmul(torch::matmul(ULt, Y), UR);  // {B,4,N,N}
  return torch::matmul(torch::matmul(VL, Z * filter), VRt);
}

}  // namespace flatnet
