#include "optics/calibrate_references.hpp"

#include "optics/calibrate.hpp"
#include "optics/camera_fit.hpp"

#include <cmath>
#include <functional>
#include <limits>
#include <iomanip>
#include <sstream>

#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet {

namespace {

using Tensors = std::vector<torch::Tensor>;

void check_pairs(const std::vector<ReferencePair>& pairs) {
  require_option(!pairs.empty(), "calibrate.references", "no pairs to calibrate from");
  const auto& first = pairs.front();
  for (const auto& p : pairs) {
    const auto where = "calibrate: pair '" + printable(p.name) + "'";
    require(p.meas.defined() && p.meas.dim() == 3 && p.meas.size(0) == 4 && p.meas.sizes() == first.meas.sizes(), where,
            "capture planes are not {4,rows,cols} like the first pair's");
    require(p.reference.defined() && p.reference.dim() == 3 && p.reference.size(0) == 4 &&
                p.reference.size(1) == p.reference.size(2) && p.reference.sizes() == first.reference.sizes(),
            where, "reference planes are not {4,N,N} like the first pair's");
    require(torch::isfinite(p.meas).all().item<bool>() && torch::isfinite(p.reference).all().item<bool>(), where,
            "holds NaN or infinity");
    // A capture or reference without contrast pins nothing down (a lens cap, a flat grey screen).
    const auto spread = [](const torch::Tensor& t) {
      return t.to(torch::kFloat64).flatten(1).std(1).min().item<double>();
    };
    require(spread(p.meas) > 1e-7, where, "its capture is flat in some channel (no signal: a lens cap, a dark frame?)");
    require(spread(p.reference) > 1e-7, where, "its reference is flat in some channel (no scene to learn from)");
  }
}

// The normal equations of one factor's step, summed over the pairs: Y_i ~ F Z_i,
// G = sum Z Z^T {4,N,N}, H = sum Y Z^T {4,m,N}.
std::pair<torch::Tensor, torch::Tensor> normal(const Tensors& Y, const Tensors& Z) {
  torch::Tensor G, H;
  for (size_t i = 0; i < Y.size(); ++i) {
    const auto g = torch::matmul(Z[i], Z[i].transpose(1, 2)), h = torch::matmul(Y[i], Z[i].transpose(1, 2));
    G = i == 0 ? g : G + g;
    H = i == 0 ? h : H + h;
  }
  return {G, H};
}

// P-step: Y_i ~ P (X_i Q^T).  Q-step: Y_i^T ~ Q (P X_i)^T.
std::pair<torch::Tensor, torch::Tensor> p_normal(const Tensors& Y, const Tensors& X, const torch::Tensor& Q) {
  Tensors Z;
  for (const auto& x : X) Z.push_back(torch::matmul(x, Q.transpose(1, 2)));
  return normal(Y, Z);
}
std::pair<torch::Tensor, torch::Tensor> q_normal(const Tensors& Y, const Tensors& X, const torch::Tensor& P) {
  Tensors Yt, Z;
  for (size_t i = 0; i < Y.size(); ++i) {
    Yt.push_back(Y[i].transpose(1, 2));
    Z.push_back(torch::matmul(P, X[i]).transpose(1, 2));
  }
  return normal(Yt, Z);
}

// The pairs' gains and offsets divided by their mean gain per channel, which is returned (P takes it):
// the scale between P and the scenes is held at the references' units.
torch::Tensor hold_mean_gain_at_one(Tensors& gain, Tensors& offset) {
  auto mean_gain = gain.front().clone();
  for (size_t i = 1; i < gain.size(); ++i) mean_gain += gain[i];
  mean_gain /= static_cast<double>(gain.size());
  require(
      mean_gain.abs().min().item<double>() > 1e-12, "calibrate",
      "the references do not explain the captures at all in some channel (wrong colour order, or unrelated pairs?)");
  for (size_t i = 0; i < gain.size(); ++i) gain[i] /= mean_gain, offset[i] /= mean_gain;
  return mean_gain;
}

// Each pair's gain and offset per channel, eq. (1), by least squares on the capture; the mean gain is
// then held at 1 (returned as its factor, for P).
torch::Tensor fit_gains(const Tensors& Y, const Tensors& R, const torch::Tensor& P, const torch::Tensor& Q,
                        Tensors& gain, Tensors& offset) {
  // The response to a uniform unit scene: (P 1)(Q 1)^T, {4,m,n}.
  const auto uniform = torch::matmul(P.sum(2, true), Q.sum(2, true).transpose(1, 2)).flatten(1);
  for (size_t i = 0; i < Y.size(); ++i) {
    const auto coded = torch::matmul(torch::matmul(P, R[i]), Q.transpose(1, 2)).flatten(1);              // {4,mn}
    const auto design = torch::stack({coded, uniform}, 2);                                               // {4,mn,2}
    const auto gram = torch::matmul(design.transpose(1, 2), design);                                     // {4,2,2}
    const auto rhs = torch::matmul(design.transpose(1, 2), Y[i].flatten(1).unsqueeze(2));                // {4,2,1}
    const auto sol = torch::linalg_solve(gram + 1e-12 * torch::eye(2, gram.options()), rhs).squeeze(2);  // {4,2}
    gain[i] = sol.select(1, 0).view({4, 1, 1});
    offset[i] = sol.select(1, 1).view({4, 1, 1});
  }
  return hold_mean_gain_at_one(gain, offset);
}

// The tensors less their mean over the pairs, and that mean: what eliminates the fixed light of (1').
std::pair<Tensors, torch::Tensor> centre_over_pairs(const Tensors& T) {
  auto mean = T.front().clone();
  for (size_t i = 1; i < T.size(); ++i) mean += T[i];
  mean /= static_cast<double>(T.size());
  Tensors centred;
  for (const auto& t : T) centred.push_back(t - mean);
  return {centred, mean};
}

// The gains and offsets of (1') with the fixed light eliminated: per channel, the least squares of
//   sum_i || (Y_i - Ybar) - sum_j (delta_ij - 1/n) (a_j D_j + b_j U) ||^2,
// D_j = (P R_j Q^T) and U = (P 1)(Q 1)^T. With K the inner products of the 2n patterns, the normal
// matrix is K (delta_jk - 1/n) and the right side <Y_j - Ybar, D_j>. The b_j's common part is not
// identified (the fixed light absorbs it): the least-norm solution, then the gauge F _|_ U. The mean
// gain is then held at 1, as in fit_gains.
// Yc, Ybar: the captures less their mean over the pairs, and that mean (centre_over_pairs).
torch::Tensor fit_gains_fixed_light(const Tensors& Yc, const torch::Tensor& Ybar, const Tensors& R,
                                    const torch::Tensor& P, const torch::Tensor& Q, Tensors& gain, Tensors& offset) {
  const auto n = static_cast<int64_t>(Yc.size());
  const auto uniform = torch::matmul(P.sum(2, true), Q.sum(2, true).transpose(1, 2)).flatten(1);  // {4,mn}
  Tensors patterns;
  std::vector<torch::Tensor> rhs;
  for (int64_t j = 0; j < n; ++j) {
    const auto coded = torch::matmul(torch::matmul(P, R[static_cast<size_t>(j)]), Q.transpose(1, 2)).flatten(1);
    patterns.push_back(coded);
    patterns.push_back(uniform);
    const auto y = Yc[static_cast<size_t>(j)].flatten(1);
    rhs.push_back((y * coded).sum(1));
    rhs.push_back((y * uniform).sum(1));
  }
  const auto D = torch::stack(patterns, 2);                                        // {4,mn,2n}
  const auto K = torch::matmul(D.transpose(1, 2), D);                              // {4,2n,2n}
  const auto pair_of = torch::arange(2 * n, torch::kLong).div(2, "floor");         // {2n}
  const auto same = (pair_of.unsqueeze(1) == pair_of.unsqueeze(0)).to(K.dtype());  // delta_jk
  const auto normal = K * (same - 1.0 / static_cast<double>(n));
  const auto sol = torch::matmul(torch::linalg_pinv(normal, 1e-10, true), torch::stack(rhs, 1).unsqueeze(2)).squeeze(2);
  // The gauge: F = Ybar - mean_j (a_j D_j + b_j U) holds nothing along U; a common offset t moves it.
  auto mean_model = torch::zeros_like(uniform);
  for (int64_t j = 0; j < n; ++j)
    mean_model += sol.select(1, 2 * j).unsqueeze(1) * patterns[static_cast<size_t>(2 * j)] +
                  sol.select(1, 2 * j + 1).unsqueeze(1) * uniform;
  const auto F = Ybar.flatten(1) - mean_model / static_cast<double>(n);
  const auto t = (F * uniform).sum(1) / uniform.square().sum(1).clamp_min(1e-300);  // {4}
  for (int64_t j = 0; j < n; ++j) {
    const auto i = static_cast<size_t>(j);
    gain[i] = sol.select(1, 2 * j).view({4, 1, 1});
    offset[i] = (sol.select(1, 2 * j + 1) + t).view({4, 1, 1});
  }
  return hold_mean_gain_at_one(gain, offset);
}

// ||Y - P X Q^T|| / ||captures|| per channel, summed over the pairs (Y and X centred over the pairs
// when the fixed light is fitted: the residual of (1') with F at its least-squares value).
std::array<double, 4> relative_residual(const Tensors& Y, const Tensors& X, const torch::Tensor& P,
                                        const torch::Tensor& Q, const Tensors& captures) {
  torch::Tensor err, norm;
  for (size_t i = 0; i < Y.size(); ++i) {
    const auto e = (Y[i] - torch::matmul(torch::matmul(P, X[i]), Q.transpose(1, 2))).square().sum({1, 2});
    const auto n = captures[i].square().sum({1, 2});
    err = i == 0 ? e : err + e;
    norm = i == 0 ? n : norm + n;
  }
  const auto rel = (err / norm.clamp_min(1e-300)).sqrt();
  std::array<double, 4> out{};
  for (int c = 0; c < 4; ++c) out[static_cast<size_t>(c)] = rel[c].item<double>();
  return out;
}

// A structured factor {C,m,N} with a random profile: the start of an alternation at a trial shift.
torch::Tensor random_structured(int64_t channels, int64_t m, int64_t N, double shift, uint64_t seed) {
  auto gen = at::detail::createCPUGenerator(seed);
  const auto length = m + static_cast<int64_t>(std::floor(std::abs(shift) * static_cast<double>(N - 1))) + 3;
  return shift_factor(at::randn({channels, length}, gen).to(torch::kFloat64), m, N, shift, 1.0);
}

// The least objective (1) reaches at a trial pair of shifts: a few alternations from a random
// structured Q. (Like a power iteration, the rank-1 bilinear fit converges from a random start.)
double objective_at(const Tensors& Y, const Tensors& X, double shift_rows, double shift_cols, int alternations,
                    uint64_t seed) {
  const int64_t n = Y.front().size(2), N = X.front().size(1);
  auto Q = random_structured(Y.front().size(0), n, N, shift_cols, seed);
  double J = 0;
  for (int a = 0; a < alternations; ++a) {
    const auto pn = p_normal(Y, X, Q);
    const auto P = solve_shift_factor(pn.first, pn.second, shift_rows).factor;
    const auto qn = q_normal(Y, X, P);
    const auto fit = solve_shift_factor(qn.first, qn.second, shift_cols);
    Q = fit.factor;
    J = fit.objective.sum().item<double>();
  }
  return J;
}

torch::Tensor bin2(const torch::Tensor& t) { return torch::avg_pool2d(t.unsqueeze(0), 2).squeeze(0); }

// Both shifts, searched on 2x2-binned captures and references (binning the sensor and the scene alike
// keeps the shift per scene pixel): first a grid of equal magnitudes (steps of 20 %) over the four
// sign pairs, each point a converged fit of both factors, then each axis's whole grid alone, then
// golden-section search within one grid step of the best point.
std::pair<double, double> search_shifts(const Tensors& Y, const Tensors& R, const ReferenceCalibrationOptions& o) {
  require_option(o.shift.min_shift >= kSmallestShiftSearched && o.shift.max_shift > o.shift.min_shift &&
                     o.shift.max_shift <= kLargestShiftSearched,
                 "calibrate.references", "the shift search needs 0.05 <= min_shift < max_shift <= 16");
  Tensors Yb, Xb;
  for (size_t i = 0; i < Y.size(); ++i) Yb.push_back(bin2(Y[i])), Xb.push_back(bin2(R[i]));
  constexpr int kAlternations = 3;
  constexpr double kGridStep = 1.2;
  std::vector<double> magnitudes;
  for (double a = o.shift.min_shift; a <= o.shift.max_shift * (1 + 1e-9); a *= kGridStep) magnitudes.push_back(a);
  double best = std::numeric_limits<double>::infinity(), rows = 0, cols = 0;
  // The grid's points: 4 sign pairs, then each axis's 2 signs, per magnitude (the golden-section
  // refinement after them costs about as much as 30 more).
  const auto points = static_cast<int64_t>(magnitudes.size()) * 8;
  Progress progress("shift search", points, o.progress);
  for (const double sign_rows : {-1.0, 1.0})
    for (const double sign_cols : {-1.0, 1.0})
      for (const double a : magnitudes) {
        const double J = objective_at(Yb, Xb, sign_rows * a, sign_cols * a, kAlternations, o.seed);
        if (J < best) best = J, rows = sign_rows * a, cols = sign_cols * a;
        progress.tick();
      }
  // Each axis alone over its whole range (the two magnitudes need not be equal).
  const auto scan = [&](const std::function<double(double)>& J, double& at) {
    for (const double sign : {-1.0, 1.0})
      for (const double a : magnitudes) {
        const double j = J(sign * a);
        if (j < best) best = j, at = sign * a;
        progress.tick();
      }
  };
  scan([&](double s) { return objective_at(Yb, Xb, s, cols, kAlternations, o.seed); }, rows);
  scan([&](double s) { return objective_at(Yb, Xb, rows, s, kAlternations, o.seed); }, cols);
  for (int round = 0; round < 2; ++round) {
    rows = golden_section_minimum([&](double s) { return objective_at(Yb, Xb, s, cols, kAlternations, o.seed); },
                                  rows / kGridStep, rows * kGridStep, 1e-3);
    cols = golden_section_minimum([&](double s) { return objective_at(Yb, Xb, rows, s, kAlternations, o.seed); },
                                  cols / kGridStep, cols * kGridStep, 1e-3);
  }
  progress.finish();
  return {rows, cols};
}

// The alternations between the mask and the kernels inside each factor's step (the outer passes
// alternate again, so a few suffice).
constexpr int kSharedMaskAlternations = 4;

// One factor's shift refined within 3 % on a step's normal equations (the other factor fixed).
double refine_shift(const std::pair<torch::Tensor, torch::Tensor>& normal_equations, double shift, double tolerance) {
  // Named, not a structured binding: a C++17 lambda may not capture one (clang refuses it).
  const auto& G = normal_equations.first;
  const auto& H = normal_equations.second;
  return golden_section_minimum([&](double s) { return solve_shift_factor(G, H, s).objective.sum().item<double>(); },
                                shift / 1.03, shift * 1.03, tolerance);
}

}  // namespace

ReferenceCalibration calibrate_from_references(const std::vector<ReferencePair>& pairs,
                                               const ReferenceCalibrationOptions& o) {
  check_pairs(pairs);
  require_option(o.passes >= 1 && o.search_passes >= 0, "calibrate.references",
                 "passes at least 1 and search passes at least 0");
  require_option(!o.shared_mask || (o.mask_taps >= 3 && o.mask_taps <= 15 && o.mask_taps % 2 == 1),
                 "calibrate.references", "a shared mask's kernels need an odd number of taps from 3 to 15");
  Tensors Y, R;
  for (const auto& p : pairs) {
    // Model (1) is centred: a plane's constant (FlatNet's centring adds the all-plane mean back) is
    // outside it, and left out of the fit and its residual.
    const auto y = p.meas.to(torch::kFloat64);
    Y.push_back(y - y.mean({1, 2}, true));
    R.push_back(p.reference.to(torch::kFloat64));
  }
  const int64_t cols = Y.front().size(2), N = R.front().size(1);
  const size_t count = pairs.size();
  require_option(!o.fixed_light || count >= 2, "calibrate.references", "a fixed light needs at least 2 pairs");
  Tensors gain(count), offset(count), X = R;  // X_i = a_i R_i + b_i, eq. (1)
  // With the fixed light, the factors see the pairs' differences from their mean (eq. 1').
  const auto for_factors = [&](const Tensors& T) { return o.fixed_light ? centre_over_pairs(T).first : T; };
  const auto [Yc, Ybar] = centre_over_pairs(Y);
  const auto& Yf = o.fixed_light ? Yc : Y;
  ReferenceCalibration result;
  const auto [shift_rows, shift_cols] = search_shifts(Yf, for_factors(R), o);
  result.shift_rows = shift_rows;
  result.shift_cols = shift_cols;
  auto Q = random_structured(4, cols, N, result.shift_cols, o.seed);
  torch::Tensor P;
  // Each plane's kernels of a shared mask (eq. 3 of shift_structure.hpp), from a unit impulse.
  auto impulse = torch::zeros({4, o.mask_taps}, torch::kFloat64);
  impulse.select(1, o.mask_taps / 2).fill_(1.0);
  auto kernels_rows = impulse.clone(), kernels_cols = impulse.clone();
  const auto solve = [&](const std::pair<torch::Tensor, torch::Tensor>& normal, double shift, torch::Tensor& kernels) {
    if (!o.shared_mask) return solve_shift_factor(normal.first, normal.second, shift);
    auto shared = solve_shared_shift_factor(normal.first, normal.second, shift, kernels, kSharedMaskAlternations);
    kernels = shared.kernels;
    return shared.fit;
  };
  Progress progress("calibrate", o.passes, o.progress);
  for (int pass = 0; pass < o.passes; ++pass) {
    // After the first pass (from a random Q), the next ones refine each shift within a few per cent of
    // the search's, at full resolution.
    const bool refine = pass >= 1 && pass <= o.search_passes;
    const auto Xf = for_factors(X);
    const auto pn = p_normal(Yf, Xf, Q);
    if (refine) result.shift_rows = refine_shift(pn, result.shift_rows, o.shift.shift_tolerance);
    auto p_fit = solve(pn, result.shift_rows, kernels_rows);
    P = p_fit.factor;
    const auto qn = q_normal(Yf, Xf, P);
    if (refine) result.shift_cols = refine_shift(qn, result.shift_cols, o.shift.shift_tolerance);
    auto q_fit = solve(qn, result.shift_cols, kernels_cols);
    Q = q_fit.factor;
    // The scale split P k, Q / k is invisible; balance it, then hold the mean gain at 1. The profiles
    // follow their factors (linear in them).
    const auto balance = (Q.norm(2, {1, 2}, true) / P.norm(2, {1, 2}, true).clamp_min(1e-300)).sqrt();  // {4,1,1}
    P = P * balance;
    Q = Q / balance;
    const auto mean_gain =
        o.fixed_light ? fit_gains_fixed_light(Yc, Ybar, R, P, Q, gain, offset) : fit_gains(Y, R, P, Q, gain, offset);
    P = P * mean_gain;
    result.profile_rows = p_fit.profile * (balance * mean_gain).view({4, 1});
    result.profile_cols = q_fit.profile / balance.view({4, 1});
    for (size_t i = 0; i < count; ++i) X[i] = gain[i] * R[i] + offset[i];
    result.residual = relative_residual(Yf, for_factors(X), P, Q, Y);
    std::ostringstream status;
    status << "shifts " << std::setprecision(4) << result.shift_rows << " " << result.shift_cols << ", residual "
           << std::setprecision(3)
           << (result.residual[0] + result.residual[1] + result.residual[2] + result.residual[3]) / 4;
    progress.set_status(status.str());
    progress.tick();
  }
  progress.finish();
  result.calib.P = P;
  result.calib.Q = Q;
  if (o.shared_mask) {
    result.kernels_rows = kernels_rows;
    result.kernels_cols = kernels_cols;
  }
  if (o.fixed_light) {  // F = mean_i (Y_i - P X_i Q^T), eq. (1')
    const auto Xbar = centre_over_pairs(X).second;
    result.calib.fixed_light = Ybar - torch::matmul(torch::matmul(P, Xbar), Q.transpose(1, 2));
  }
  for (size_t i = 0; i < count; ++i) {
    std::array<double, 8> g{};
    for (int c = 0; c < 4; ++c) {
      g[static_cast<size_t>(c)] = gain[i][c].item<double>();
      g[static_cast<size_t>(4 + c)] = offset[i][c].item<double>();
    }
    result.gain_offset.push_back(g);
    const auto means = X[i].mean({1, 2});
    result.scene_means.push_back(
        {means[0].item<double>(), means[1].item<double>(), means[2].item<double>(), means[3].item<double>()});
  }
  return result;
}

std::string describe_shared_mask(const ReferenceCalibration& fit) {
  if (!fit.kernels_rows.defined()) return "";
  std::ostringstream os;
  os << std::fixed << std::setprecision(2)
     << "one mask per axis for the four planes (--shared-mask), each plane's kernel (offset, blur in sensor pixels)";
  const char* names[4] = {"b", "gb", "gr", "r"};
  for (const auto& [axis, k] :
       {std::pair<const char*, torch::Tensor>{"rows", fit.kernels_rows}, {"cols", fit.kernels_cols}}) {
    os << "; " << axis << ":";
    const auto taps = k.size(1);
    const auto tau = torch::arange(taps, torch::kFloat64) - static_cast<double>(taps / 2);
    for (int64_t c = 0; c < k.size(0); ++c) {
      const auto w = k[c].abs();
      const double total = std::max(1e-300, w.sum().item<double>());
      const double centre = (w * tau).sum().item<double>() / total;
      const double width = std::sqrt((w * (tau - centre).square()).sum().item<double>() / total);
      os << " " << names[c] << " " << centre << " " << width;
    }
  }
  return os.str();
}

std::array<double, 4> reference_correlation(const torch::Tensor& reconstruction, const torch::Tensor& reference) {
  std::array<double, 4> out{};
  for (int c = 0; c < 4; ++c) {
    const auto ref = reference[c].to(torch::kFloat64), rec = reconstruction[c].to(torch::kFloat64);
    const auto kept = ref > 0;  // pixels clipped at zero hold no value
    auto a = rec.masked_select(kept), b = ref.masked_select(kept);
    if (a.numel() < 2) continue;
    a = a - a.mean();
    b = b - b.mean();
    out[static_cast<size_t>(c)] = ((a * b).sum() / (a.norm() * b.norm()).clamp_min(1e-300)).item<double>();
  }
  return out;
}

double open_light_of(const std::vector<torch::Tensor>& levels, const ReferenceCalibration& fit, double dark) {
  double xy = 0, xx = 0;
  for (size_t i = 0; i < levels.size() && i < fit.scene_means.size(); ++i) {
    const auto level = levels[i].to(torch::kFloat64).flatten();
    for (int c = 0; c < 4; ++c) {
      const double scene_mean = fit.scene_means[i][static_cast<size_t>(c)];
      xy += scene_mean * (level[c].item<double>() - dark), xx += scene_mean * scene_mean;
    }
  }
  const double k = xx > 0 ? xy / xx : 0.0;
  return std::isfinite(k) && k > 0 && k <= 1e3 ? k : 0.0;
}

WhiteFrameFit fit_white_frame(const torch::Tensor& planes, const Calibration& calib, double relative_lambda) {
  require(planes.dim() == 3 && planes.size(0) == 4 && planes.size(1) == calib.P.size(1) &&
              planes.size(2) == calib.Q.size(1),
          "calibrate", "the white capture's planes do not match the calibration's window");
  // Eq. (2) is fitted on the singular pairs the camera measures above its regulariser (s_L s_R >=
  // sqrt(lambda), as the data-consistency step keeps): elsewhere the sensor's noise is most of what
  // a capture holds, and a residual there would not tell a white from a scene.
  const auto inverse = separable_inverse(calib.P, calib.Q, 1.0);
  const double lambda = absolute_tikhonov_lambda(inverse, relative_lambda);
  const auto measured = well_measured_pairs(inverse.sL, inverse.sR, lambda);  // {4,N,N}
  const auto coefficients = [&](const torch::Tensor& Y) {  // U_L^T Y U_R on the measured pairs, {4,N,N}
    return torch::matmul(torch::matmul(inverse.ULt.to(torch::kFloat64), Y), inverse.UR.to(torch::kFloat64)) * measured;
  };
  // Eq. (2)'s pattern: a uniform scene's shadow, double-centred as the capture is.
  auto U = torch::einsum("ci,cj->cij", {calib.P.to(torch::kFloat64).sum(2), calib.Q.to(torch::kFloat64).sum(2)});
  U = U - U.mean(1, true) - U.mean(2, true) + U.mean({1, 2}, true);
  // The white capture holds the fixed light as every capture does (eq. 1'): it is not the white's.
  const auto CU = coefficients(U),
             CY = coefficients(without_fixed_light(planes.to(torch::kFloat64), calib.fixed_light));
  WhiteFrameFit out;
  for (int c = 0; c < 4; ++c) {
    const double uu = CU[c].square().sum().item<double>(), yy = CY[c].square().sum().item<double>();
    const double m = uu > 0 ? (CU[c] * CY[c]).sum().item<double>() / uu : 0.0;
    out.level[static_cast<size_t>(c)] = m;
    out.residual[static_cast<size_t>(c)] = yy > 0 ? (CY[c] - m * CU[c]).norm().item<double>() / std::sqrt(yy) : 1.0;
  }
  return out;
}

void rescale_scene_units(ReferenceCalibration& fit, const std::array<double, 4>& scale) {
  for (int c = 0; c < 4; ++c) {
    const double s = scale[static_cast<size_t>(c)];
    require(std::isfinite(s) && s > 0, "calibrate", "a scene unit must be a positive, finite scale");
    const double k = 1.0 / std::sqrt(s);
    fit.calib.P[c].mul_(k);
    fit.calib.Q[c].mul_(k);
    if (fit.profile_rows.defined()) fit.profile_rows[c].mul_(k);
    if (fit.profile_cols.defined()) fit.profile_cols[c].mul_(k);
    for (auto& g : fit.gain_offset) g[static_cast<size_t>(c)] *= s, g[static_cast<size_t>(4 + c)] *= s;
    for (auto& m : fit.scene_means) m[static_cast<size_t>(c)] *= s;
  }
}

double typical_scene_scale(const ReferenceCalibration& fit, double light) {
  require(std::isfinite(light) && light > 0, "calibrate", "a scene's light must be positive and finite");
  if (fit.scene_means.empty()) return 0;
  double log_sum = 0;
  for (const auto& means : fit.scene_means) {
    const double mean = (means[0] + means[1] + means[2] + means[3]) / 4;
    if (!(std::isfinite(mean) && mean > 0)) return 0;
    log_sum += std::log(mean);
  }
  return light / std::exp(log_sum / static_cast<double>(fit.scene_means.size()));
}

double absolute_tikhonov_lambda(const SeparableInverse& inverse, double relative) {
  const double top = (inverse.sL.select(1, 0) * inverse.sR.select(1, 0)).max().item<double>();
  return relative * top * top;
}

std::vector<HeldOutPair> leave_one_out(const std::vector<ReferencePair>& pairs, double lambda,
                                       const ReferenceCalibrationOptions& options, const Calibration* whole) {
  require_option(pairs.size() >= 3, "calibrate.references", "leave-one-out needs at least 3 pairs");
  std::vector<HeldOutPair> out;
  // Each held-out fit is a whole calibration: the bar says which pair is out, and the time left.
  Progress progress("leave-one-out", static_cast<int64_t>(pairs.size()), options.progress);
  for (size_t held = 0; held < pairs.size(); ++held) {
    progress.set_status("without " + printable(pairs[held].name));
    std::vector<ReferencePair> others;
    for (size_t i = 0; i < pairs.size(); ++i)
      if (i != held) others.push_back(pairs[i]);
    auto o = options;
    o.progress = false;
    const auto fit = calibrate_from_references(others, o);
    const auto inverse = separable_inverse(fit.calib.P, fit.calib.Q, 1.0);
    const auto filter = tikhonov_filter(inverse.sL, inverse.sR, absolute_tikhonov_lambda(inverse, lambda));
    // The held-out capture less the light the others' fit found on every capture (eq. 1').
    const auto meas = without_fixed_light(pairs[held].meas.to(torch::kFloat64), fit.calib.fixed_light);
    const auto rec = apply_separable_inverse(inverse.ULt, inverse.UR, inverse.VL, inverse.VRt, filter,
                                             meas.to(torch::kFloat32).unsqueeze(0))[0];
    HeldOutPair h{pairs[held].name, reference_correlation(rec, pairs[held].reference), fit.shift_rows, fit.shift_cols};
    // The camera fit's near-twin statistic of a capture this calibration did not see: what a new
    // capture of the camera shows (optics/camera_fit.hpp), where the pairs' own understate it.
    const auto U = std::get<0>(torch::linalg_qr(fit.calib.P)).to(torch::kFloat32);
    const auto V = std::get<0>(torch::linalg_qr(fit.calib.Q)).to(torch::kFloat32);
    const double leak = coded_leak(meas.to(torch::kFloat32), U, V);  // nan where not measurable
    if (std::isfinite(leak)) h.leak = leak;
    if (whole) {
      const auto change = calibration_error(fit.calib, *whole, pairs[held].reference);
      h.change_p = change.p;
      h.change_q = change.q;
      h.change_coded = change.forward;
    }
    out.push_back(h);
    progress.tick();
  }
  progress.finish();
  return out;
}

}  // namespace flatnet
