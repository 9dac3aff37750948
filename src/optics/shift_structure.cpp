#include "optics/shift_structure.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "core/error.hpp"

namespace flatnet {

namespace {

// Where each entry (i,j) of a factor reads the profile: samples k and k + 1, weights 1 - w and w (eq. 1).
struct Sampling {
  torch::Tensor index;   // {2 m N} long: k for every entry, then k + 1
  torch::Tensor weight;  // {2 m N} float64: 1 - w, then w
  int64_t length = 0;    // the profile's samples
};

Sampling sampling(int64_t rows, int64_t scene, double shift, double spacing) {
  require_option(std::isfinite(shift) && shift != 0 && spacing > 0, "calibrate.dataset",
                 "a shift structure needs a non-zero shift and a positive spacing");
  const auto f64 = torch::TensorOptions().dtype(torch::kFloat64);
  const auto pos = torch::arange(rows, f64).view({rows, 1}) + torch::arange(scene, f64).view({1, scene}) * shift;
  const double lowest = shift < 0 ? static_cast<double>(scene - 1) * shift : 0.0;
  const auto u = ((pos - lowest) / spacing).flatten();
  const auto floor = u.floor();
  const auto k = floor.to(torch::kLong);
  const auto w = u - floor;
  Sampling s;
  s.index = torch::cat({k, k + 1});
  s.weight = torch::cat({1 - w, w});
  s.length = k.max().item<int64_t>() + 2;
  return s;
}

torch::Tensor centre_columns(const torch::Tensor& F) { return F - F.mean(1, true); }

// F(f) {C,m,N} from the profile {C,L}.
torch::Tensor expand(const torch::Tensor& f, const Sampling& s, int64_t rows, int64_t scene) {
  return (f.index_select(1, s.index) * s.weight).view({f.size(0), 2, rows, scene}).sum(1);
}

// The adjoint of expand: {C,m,N} -> {C,L}. (scatter_add_ along a row is several times faster here
// than index_add_ on dimension 1.)
torch::Tensor gather_back(const torch::Tensor& R, const Sampling& s) {
  const auto r = R.reshape({R.size(0), -1}).repeat({1, 2}) * s.weight;
  return torch::zeros({R.size(0), s.length}, R.options()).scatter_add_(1, s.index.expand({R.size(0), -1}), r);
}

// J of eq. (2) per channel.
torch::Tensor objective(const torch::Tensor& F, const torch::Tensor& G, const torch::Tensor& H) {
  return (torch::matmul(F, G) * F).sum({1, 2}) - 2 * (F * H).sum({1, 2});
}

}  // namespace

int64_t shift_profile_length(int64_t rows, int64_t scene, double shift, double spacing) {
  return sampling(rows, scene, shift, spacing).length;
}

torch::Tensor shift_factor(const torch::Tensor& profile, int64_t rows, int64_t scene, double shift, double spacing) {
  const auto s = sampling(rows, scene, shift, spacing);
  require_option(profile.dim() == 2 && profile.size(1) >= s.length, "calibration",
                 "a shift profile needs " + std::to_string(s.length) + " samples for this geometry and shift");
  return centre_columns(expand(profile, s, rows, scene));
}

ShiftFactor fit_shift_factor(const torch::Tensor& G, const torch::Tensor& H, double shift, const ShiftFitOptions& o,
                             int max_iterations, const torch::Tensor& warm) {
  const auto g = G.to(torch::kFloat64), h = H.to(torch::kFloat64);  // {C,N,N}, {C,m,N}
  const int64_t rows = h.size(1), scene = h.size(2);
  const auto s = sampling(rows, scene, shift, o.spacing);
  // The profile's constant is invisible in centred captures (C F(f + a) = C F(f)); a whisper of ridge
  // keeps it at zero.
  const auto ridge = (1e-10 * static_cast<double>(rows * scene) / static_cast<double>(s.length)) *
                     g.diagonal(0, 1, 2).mean(1, true).clamp_min(1e-300);  // {C,1}
  const auto normal = [&](const torch::Tensor& f) {                        // the normal equations' operator on f
    return gather_back(torch::matmul(centre_columns(expand(f, s, rows, scene)), g), s) + ridge * f;
  };
  const auto b = gather_back(h, s);
  auto x = warm.defined() && warm.sizes() == b.sizes() ? warm.to(torch::kFloat64).clone() : torch::zeros_like(b);
  auto r = b - normal(x);
  auto p = r.clone();
  auto rr = r.square().sum(1, true);
  const auto stop = (o.cg_tolerance * b.norm(2, 1, true)).square();
  for (int it = 0; it < max_iterations && (rr > stop).any().item<bool>(); ++it) {
    const auto Ap = normal(p);
    const auto alpha = rr / (p * Ap).sum(1, true).clamp_min(1e-300);
    x += alpha * p;
    r -= alpha * Ap;
    const auto next = r.square().sum(1, true);
    p = r + (next / rr.clamp_min(1e-300)) * p;
    rr = next;
  }
  ShiftFactor out;
  out.shift = shift;
  out.profile = x;
  out.factor = centre_columns(expand(x, s, rows, scene));
  out.objective = objective(out.factor, g, h);
  return out;
}

ShiftNormalEquations shift_normal_equations(const torch::Tensor& G, const torch::Tensor& H, double shift) {
  require_option(std::isfinite(shift) && shift != 0, "calibrate.dataset", "a shift structure needs a non-zero shift");
  const auto g = G.to(torch::kFloat64), h = H.to(torch::kFloat64);  // {C,N,N}, {C,m,N}
  const int64_t channels = h.size(0), rows = h.size(1), scene = h.size(2);
  const auto f64 = torch::TensorOptions().dtype(torch::kFloat64);
  // Row 0 reads samples d_j and d_j + 1 with weights 1 - w_j and w_j (eq. 1, spacing 1).
  const double lowest = shift < 0 ? static_cast<double>(scene - 1) * shift : 0.0;
  const auto pos = torch::arange(scene, f64) * shift - lowest;
  const auto d = pos.floor().to(torch::kLong);
  const auto w = pos - pos.floor();
  const int64_t width = d.max().item<int64_t>() + 2, length = rows + width - 1;
  const auto j = torch::arange(scene, torch::kLong);
  auto T0 = torch::zeros({scene, width}, f64);
  T0.index_put_({j, d}, 1 - w, true);
  T0.index_put_({j, d + 1}, w, true);
  const auto M0 = torch::matmul(torch::matmul(T0.t(), g), T0);  // {C,W,W}
  // Diag[c, delta + W - 1, a] = M0[c, a, a + delta], then windowed sums of m along a.
  const auto delta = torch::arange(-(width - 1), width, torch::kLong).view({-1, 1});
  const auto a = torch::arange(width, torch::kLong).view({1, -1}).expand({2 * width - 1, width});
  const auto b = a + delta;
  const auto inside = ((b >= 0) & (b < width)).to(torch::kFloat64);
  const auto diag = M0.index({torch::indexing::Slice(), a, b.clamp(0, width - 1)}) * inside;    // {C,2W-1,W}
  const auto cumulative = torch::cumsum(torch::constant_pad_nd(diag, {1, length - width}), 2);  // {C,2W-1,L+1}
  const auto k = torch::arange(length, torch::kLong);
  const auto windowed = cumulative.index_select(2, (k + 1).clamp_max(length)) -
                        cumulative.index_select(2, (k + 1 - rows).clamp_min(0));  // {C,2W-1,L}
  const auto kk = k.view({1, -1}).expand({2 * width - 1, length});
  const auto ll = kk + delta;
  const auto valid = (ll >= 0) & (ll < length);
  auto A = torch::zeros({channels, length, length}, f64);
  A.index_put_({torch::indexing::Slice(), kk.masked_select(valid), ll.masked_select(valid)},
               windowed.masked_select(valid.unsqueeze(0)).view({channels, -1}));
  // The centring: S[j,k] = (1 - w_j) [d_j <= k < d_j + m] + w_j [d_j + 1 <= k < d_j + 1 + m].
  auto S = torch::zeros({scene, length + 1}, f64);
  S.index_put_({j, d}, 1 - w, true);
  S.index_put_({j, d + rows}, -(1 - w), true);
  S.index_put_({j, d + 1}, w, true);
  S.index_put_({j, (d + 1 + rows).clamp_max(length)}, -w, true);
  S = torch::cumsum(S, 1).narrow(1, 0, length);
  A -= torch::matmul(torch::matmul(S.t(), g), S) / static_cast<double>(rows);
  // The right-hand side: the adjoint of f -> F applied to the centred H.
  const auto hc = h - h.mean(1, true);
  const auto index = (torch::arange(rows, torch::kLong).view({-1, 1}) + d.view({1, -1})).flatten();
  auto rhs = torch::zeros({channels, length}, f64);
  rhs.index_add_(1, index, (hc * (1 - w)).flatten(1));
  rhs.index_add_(1, index + 1, (hc * w).flatten(1));
  // The profile's constant is invisible in centred captures: a whisper of ridge keeps it at zero.
  const auto ridge = 1e-8 * static_cast<double>(rows * scene) / static_cast<double>(length) *
                     g.diagonal(0, 1, 2).mean(1).clamp_min(1e-300).view({channels, 1, 1});
  ShiftNormalEquations out;
  out.A = A + ridge * torch::eye(length, f64);
  out.rhs = rhs;
  return out;
}

ShiftFactor solve_shift_factor(const torch::Tensor& G, const torch::Tensor& H, double shift) {
  const auto eq = shift_normal_equations(G, H, shift);
  const auto f = torch::linalg_solve(eq.A, eq.rhs.unsqueeze(2)).squeeze(2);
  ShiftFactor out;
  out.shift = shift;
  out.profile = f;
  out.factor = shift_factor(f, H.size(1), H.size(2), shift, 1.0);
  out.objective = objective(out.factor, G.to(torch::kFloat64), H.to(torch::kFloat64));
  return out;
}

namespace {

// K^T A K for the convolution (K p)[t] = sum_tau k[tau] p[t - tau], tau = -h..h, zero beyond the
// ends: (K^T A K)[u,v] = sum_{tau,tau'} k[tau] k[tau'] A[u + tau, v + tau'].
torch::Tensor convolved_normal(const torch::Tensor& A, const torch::Tensor& k) {  // A {L,L}, k {K}
  const int64_t L = A.size(0), K = k.size(0), h = K / 2;
  const auto padded = torch::constant_pad_nd(A, {h, h, h, h});
  auto out = torch::zeros_like(A);
  for (int64_t a = 0; a < K; ++a)
    for (int64_t b = 0; b < K; ++b) out += k[a] * k[b] * padded.narrow(0, a, L).narrow(1, b, L);
  return out;
}

// K^T r: (K^T r)[u] = sum_tau k[tau] r[u + tau].
torch::Tensor convolved_rhs(const torch::Tensor& r, const torch::Tensor& k) {  // r {L}, k {K}
  const int64_t L = r.size(0), K = k.size(0), h = K / 2;
  const auto padded = torch::constant_pad_nd(r, {h, h});
  auto out = torch::zeros_like(r);
  for (int64_t a = 0; a < K; ++a) out += k[a] * padded.narrow(0, a, L);
  return out;
}

// The profile's copies that a kernel weighs: M[t, a] = p[t - (a - h)], so K p = M k.  {L,K}
torch::Tensor shifted_copies(const torch::Tensor& p, int64_t taps) {
  const int64_t L = p.size(0), h = taps / 2;
  const auto padded = torch::constant_pad_nd(p, {h, h});
  std::vector<torch::Tensor> columns;
  for (int64_t a = 0; a < taps; ++a) columns.push_back(padded.narrow(0, 2 * h - a, L));
  return torch::stack(columns, 1);
}

// min k^T A k - 2 r^T k over k >= 0 (A {K,K} positive definite, K small), by cyclic coordinate
// descent from `start` (clamped): each coordinate exactly minimised in turn, which converges for a
// convex quadratic under bounds. A kernel is a blur moved by a sub-pixel offset: light is spread,
// never subtracted, so its taps are not negative (what a mask is, not what the references blur away).
torch::Tensor nonnegative_least_squares(const torch::Tensor& A, const torch::Tensor& r, const torch::Tensor& start) {
  const int64_t K = r.size(0);
  auto a = A.contiguous(), b = r.contiguous();
  const double* Ap = a.data_ptr<double>();
  const double* rp = b.data_ptr<double>();
  std::vector<double> k(static_cast<size_t>(K));
  for (int64_t i = 0; i < K; ++i) k[static_cast<size_t>(i)] = std::max(0.0, start[i].item<double>());
  for (int sweep = 0; sweep < 500; ++sweep) {
    double moved = 0, size = 0;
    for (int64_t i = 0; i < K; ++i) {
      double rest = rp[i];
      for (int64_t j = 0; j < K; ++j)
        if (j != i) rest -= Ap[i * K + j] * k[static_cast<size_t>(j)];
      const double next = Ap[i * K + i] > 0 ? std::max(0.0, rest / Ap[i * K + i]) : 0.0;
      moved += std::abs(next - k[static_cast<size_t>(i)]);
      size += std::abs(next);
      k[static_cast<size_t>(i)] = next;
    }
    if (moved <= 1e-12 * std::max(size, 1e-300)) break;
  }
  return torch::tensor(k, torch::kFloat64);
}

// The kernel's sign is a channel's own (P_c and Q_c may both change sign: their product is what the
// captures see), so the kernel is the better of a non-negative and a non-positive one.
torch::Tensor signed_nonnegative_least_squares(const torch::Tensor& A, const torch::Tensor& r,
                                               const torch::Tensor& start) {
  const auto positive = nonnegative_least_squares(A, r, start);
  const auto negative = -nonnegative_least_squares(A, -r, -start);
  const auto J = [&](const torch::Tensor& k) {
    return (torch::dot(k, torch::mv(A, k)) - 2 * torch::dot(r, k)).item<double>();
  };
  return J(positive) <= J(negative) ? positive : negative;
}

}  // namespace

SharedShiftFactor solve_shared_shift_factor(const torch::Tensor& G, const torch::Tensor& H, double shift,
                                            const torch::Tensor& kernels, int alternations) {
  const auto eq = shift_normal_equations(G, H, shift);  // A {C,L,L}, rhs {C,L}
  const int64_t channels = eq.rhs.size(0), length = eq.rhs.size(1);
  require_option(
      kernels.dim() == 2 && kernels.size(0) == channels && kernels.size(1) % 2 == 1 && kernels.size(1) < length,
      "calibrate.references", "a shared mask needs one odd kernel per channel");
  auto k = kernels.to(torch::kFloat64).clone();  // {C,K}
  const int64_t taps = k.size(1);
  torch::Tensor mask;
  for (int it = 0; it < std::max(1, alternations); ++it) {
    // The mask for fixed kernels: sum_c K_c^T A_c K_c m = sum_c K_c^T rhs_c (eq. 3).
    auto A = torch::zeros({length, length}, eq.A.options());
    auto r = torch::zeros({length}, eq.A.options());
    for (int64_t c = 0; c < channels; ++c) {
      A += convolved_normal(eq.A[c], k[c]);
      r += convolved_rhs(eq.rhs[c], k[c]);
    }
    mask = torch::linalg_solve(A, r.unsqueeze(1)).squeeze(1);
    // Each channel's kernel for the fixed mask: eq. 3's J as a K x K least squares in k_c.
    const auto M = shifted_copies(mask, taps);  // {L,K}
    for (int64_t c = 0; c < channels; ++c) {
      const auto Ak = torch::matmul(torch::matmul(M.t(), eq.A[c]), M);
      const auto rk = torch::matmul(M.t(), eq.rhs[c]);
      k[c] = signed_nonnegative_least_squares(Ak, rk, k[c]);
    }
    // The gauge: the kernels' mean |sum| is 1 (the mask carries the scale).
    const auto scale = k.sum(1).abs().mean();
    if (std::abs(scale.item<double>()) > 1e-300) {
      k /= scale;
      mask = mask * scale;
    }
  }
  SharedShiftFactor out;
  out.mask = mask;
  out.kernels = k;
  const auto profile = torch::matmul(k, shifted_copies(mask, taps).t());  // {C,L}: f_c = M k_c
  out.fit.shift = shift;
  out.fit.profile = profile;
  out.fit.factor = shift_factor(profile, H.size(1), H.size(2), shift, 1.0);
  out.fit.objective = objective(out.fit.factor, G.to(torch::kFloat64), H.to(torch::kFloat64));
  return out;
}

double search_shift(const torch::Tensor& G, const torch::Tensor& H, const ShiftFitOptions& o, double sigma2) {
  require_option(o.min_shift >= kSmallestShiftSearched && o.max_shift > o.min_shift &&
                     o.max_shift <= kLargestShiftSearched && o.grid_step >= kFinestShiftGridStep &&
                     o.shift_tolerance > 0,
                 "calibrate.dataset",
                 "the shift search needs 0.05 <= min_shift < max_shift <= 16 and a grid step of at least 0.01");
  const auto cost = [&](double shift, int iterations) {
    const auto fit = fit_shift_factor(G, H, shift, o, iterations);
    const auto channels = static_cast<double>(fit.profile.size(0)), samples = static_cast<double>(fit.profile.size(1));
    return fit.objective.sum().item<double>() + 2 * sigma2 * samples * channels;
  };
  // The coarse grid, one sign at a time: the bracket is the best point's two neighbours.
  double lo = 0, hi = 0, best = std::numeric_limits<double>::infinity();
  for (const double sign : {-1.0, 1.0}) {
    std::vector<double> grid;
    for (double a = o.min_shift; a <= o.max_shift * (1 + 1e-9); a *= 1 + o.grid_step) grid.push_back(sign * a);
    for (size_t i = 0; i < grid.size(); ++i) {
      const double j = cost(grid[i], o.search_iterations);
      if (j < best) {
        best = j;
        lo = grid[i > 0 ? i - 1 : i];
        hi = grid[i + 1 < grid.size() ? i + 1 : i];
      }
    }
  }
  return golden_section_minimum([&](double shift) { return cost(shift, o.fit_iterations); }, lo, hi, o.shift_tolerance);
}

double golden_section_minimum(const std::function<double(double)>& f, double lo, double hi, double tolerance) {
  const double ratio = (std::sqrt(5.0) - 1) / 2;
  double a = std::min(lo, hi), b = std::max(lo, hi);
  double c = b - ratio * (b - a), d = a + ratio * (b - a);
  double fc = f(c), fd = f(d);
  while (b - a > tolerance * std::max(std::abs(a), std::abs(b))) {
    if (fc < fd) {
      b = d;
      d = c;
      fd = fc;
      c = b - ratio * (b - a);
      fc = f(c);
    } else {
      a = c;
      c = d;
      fc = fd;
      d = a + ratio * (b - a);
      fd = f(d);
    }
  }
  return fc < fd ? c : d;
}

}  // namespace flatnet
