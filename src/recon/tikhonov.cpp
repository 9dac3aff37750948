#include "recon/tikhonov.hpp"

#include "nn/onednn_conv.hpp"

namespace flatnet {

Tikhonov::Tikhonov(const Calibration& calib, double lambda)
    : lambda_(lambda), inverse_(separable_inverse(calib.P, calib.Q, lambda)) {}

void Tikhonov::set_lambda(double lambda) {
  lambda_ = lambda;
  inverse_.filter = tikhonov_filter(inverse_.sL, inverse_.sR, lambda);
}

torch::Tensor Tikhonov::operator()(const torch::Tensor& Y) const {  // {B,4,h,w} -> {B,4,N,N}
  const auto& v = inverse_;
  if (Y.requires_grad() || Y.dim() != 4 || Y.size(1) != 4)
    return apply_separable_inverse(v.ULt, v.UR, v.VL, v.VRt, v.filter, Y);
  // The same products (thesis eq. 2.6) through oneDNN's fp32 GEMM (nn/onednn_conv.hpp), the
  // cheaper order first: UL^T (Y UR) is 2 N h (w + N) per plane against 2 N w (h + N).
  const int64_t B = Y.size(0), h = Y.size(2), w = Y.size(3), N = v.VL.size(1);
  const auto Yc = Y.to(torch::kFloat32).reshape({B * 4, h, w});
  const auto per_plane = [&](const torch::Tensor& m) {  // {4,r,c} -> {B*4,r,c} (a view when B is 1)
    return B == 1 ? m : m.unsqueeze(0).expand({B, 4, m.size(1), m.size(2)}).reshape({B * 4, m.size(1), m.size(2)});
  };
  const auto Z = onednn_bmm(per_plane(v.ULt), onednn_bmm(Yc, per_plane(v.UR)));  // {B*4,N,N}
  const auto filtered = (Z.view({B, 4, N, N}) * v.filter).reshape({B * 4, N, N});
  return onednn_bmm(onednn_bmm(per_plane(v.VL), filtered), per_plane(v.VRt)).view({B, 4, N, N});
}

namespace {

using torch::indexing::None;
using torch::indexing::Slice;

}  // namespace

std::pair<torch::Tensor, torch::Tensor> tv_gradient(const torch::Tensor& x) {
  auto gx = torch::zeros_like(x), gy = torch::zeros_like(x);
  gx.index_put_({"...", Slice(), Slice(0, -1)},
                x.index({"...", Slice(), Slice(1, None)}) - x.index({"...", Slice(), Slice(0, -1)}));
  gy.index_put_({"...", Slice(0, -1), Slice()},
                x.index({"...", Slice(1, None), Slice()}) - x.index({"...", Slice(0, -1), Slice()}));
  return {gx, gy};
}
torch::Tensor tv_divergence(const torch::Tensor& px, const torch::Tensor& py) {
  auto dx = px.clone(), dy = py.clone();
  dx.index_put_({"...", Slice(), Slice(1, None)},
                px.index({"...", Slice(), Slice(1, None)}) - px.index({"...", Slice(), Slice(0, -1)}));
  dx.index_put_({"...", Slice(), -1}, -px.index({"...", Slice(), -2}));
  dy.index_put_({"...", Slice(1, None), Slice()},
                py.index({"...", Slice(1, None), Slice()}) - py.index({"...", Slice(0, -1), Slice()}));
  dy.index_put_({"...", -1, Slice()}, -py.index({"...", -2, Slice()}));
  return dx + dy;
}

namespace {

// prox of t*TV plus the constraint X >= 0 at point b, by FGP (Beck & Teboulle 2009) on the dual:
// TV(x) = max_{|p|<=1} <-div p, x>, so x(p) = P_{x>=0}(b + t div p) and p ascends along grad x(p) / (8t).
torch::Tensor tv_prox_nonneg(const torch::Tensor& b, double t, int iterations) {
  auto px = torch::zeros_like(b), py = torch::zeros_like(b);
  auto rx = px, ry = py;
  double tk = 1.0;
  for (int k = 0; k < iterations; ++k) {
    auto x = (b + t * tv_divergence(rx, ry)).clamp_min(0);
    auto [gx, gy] = tv_gradient(x);
    auto qx = rx + gx / (8.0 * t), qy = ry + gy / (8.0 * t);
    auto norm = torch::sqrt(qx * qx + qy * qy).clamp_min(1.0);  // project onto unit ball
    auto nx = qx / norm, ny = qy / norm;
    const double tn = (1 + std::sqrt(1 + 4 * tk * tk)) / 2;
    rx = nx + ((tk - 1) / tn) * (nx - px);
    ry = ny + ((tk - 1) / tn) * (ny - py);
    px = nx;
    py = ny;
    tk = tn;
  }
  return (b + t * tv_divergence(px, py)).clamp_min(0);
}

}  // namespace

TVSolver::TVSolver(const Calibration& calib, TVOptions options) : opt_(options), init_(calib, options.tikhonov_lambda) {
  P_ = calib.P.to(torch::kFloat32).contiguous();
  Q_ = calib.Q.to(torch::kFloat32).contiguous();
  auto nP = torch::linalg_matrix_norm(calib.P.to(torch::kFloat64), 2);  // {4}
  auto nQ = torch::linalg_matrix_norm(calib.Q.to(torch::kFloat64), 2);
  lipschitz_ = (nP * nP * nQ * nQ).max().item<double>();
}

torch::Tensor TVSolver::operator()(const torch::Tensor& Y) const {
  auto Qt = Q_.transpose(1, 2), Pt = P_.transpose(1, 2);
  auto x = init_(Y).clamp_min(0);
  auto z = x;
  double tk = 1.0;
  const double step = 1.0 / lipschitz_;
  for (int k = 0; k < opt_.iterations; ++k) {
    auto residual = torch::matmul(torch::matmul(P_, z), Qt) - Y;  // {B,4,h,w}
    auto g = torch::matmul(torch::matmul(Pt, residual), Q_);      // {B,4,N,N}
    auto xn = tv_prox_nonneg(z - step * g, step * opt_.lambda, opt_.prox_iterations);
    const double tn = (1 + std::sqrt(1 + 4 * tk * tk)) / 2;
    z = xn + ((tk - 1) / tn) * (xn - x);
    x = xn;
    tk = tn;
  }
  return x;
}

}  // namespace flatnet
