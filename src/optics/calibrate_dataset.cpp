#include "optics/calibrate_dataset.hpp"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <limits>
#include <sstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "optics/camera_fit.hpp"

namespace flatnet {

namespace {

// The display's primaries {3,N,N} (R, G, B) of a pair's scene planes {4,N,N} (b, g, g, r).
torch::Tensor primaries(const torch::Tensor& scene) { return torch::stack({scene[3], scene[1], scene[0]}); }

// The mix that means none: b sees B, gb and gr G, r R.
torch::Tensor unmixed() {
  return torch::tensor({0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0}, torch::kFloat64).view({4, 3});
}

// The pairs, decoded once where the memory budget allows and read again in every pass otherwise.
class PairStream {
 public:
  PairStream(int64_t count, std::function<CapturePair(int64_t)> load, int64_t rows, int64_t cols, int64_t scene,
             int64_t cache_bytes)
      : count_(count), load_(std::move(load)), rows_(rows), cols_(cols), scene_(scene) {
    const int64_t pair_bytes = 4 * 4 * (rows * cols + scene * scene);
    cached_ = std::min<int64_t>(count, std::max<int64_t>(0, cache_bytes) / pair_bytes);
  }
  int64_t size() const { return count_; }
  // Pair i with its scene as the planes see it through the colour mix (set_mix; none at first).
  CapturePair get(int64_t i) {
    auto p = get_unmixed(i);
    if (mix_.defined()) p.scene = scene_through_mix(p.scene, mix_);
    return p;
  }
  CapturePair get_unmixed(int64_t i) {
    if (i < static_cast<int64_t>(cache_.size())) return cache_[static_cast<size_t>(i)];
    auto p = checked(i);
    if (i < cached_ && i == static_cast<int64_t>(cache_.size())) cache_.push_back(p);
    return p;
  }
  void set_mix(const torch::Tensor& mix) { mix_ = mix.to(torch::kFloat32); }

 private:
  CapturePair checked(int64_t i) {
    auto p = load_(i);
    const auto where = option_key("calibrate.dataset") + " pair " + std::to_string(i);
    require(p.meas.defined() && p.meas.sizes() == torch::IntArrayRef({4, rows_, cols_}), where,
            "capture planes are not {4," + std::to_string(rows_) + "," + std::to_string(cols_) + "}");
    require(p.scene.defined() && p.scene.sizes() == torch::IntArrayRef({4, scene_, scene_}), where,
            "scene planes are not {4," + std::to_string(scene_) + "," + std::to_string(scene_) + "}");
    p.meas = p.meas.to(torch::kFloat32).contiguous();
    if (p.level.defined()) {
      require(p.level.numel() == 4, where, "level is not one value per plane");
      p.level = p.level.to(torch::kFloat64).flatten();
    }
    p.scene = p.scene.to(torch::kFloat32).contiguous();
    require(torch::isfinite(p.meas).all().item<bool>() && torch::isfinite(p.scene).all().item<bool>(), where,
            "holds NaN or infinity");
    return p;
  }
  int64_t count_;
  std::function<CapturePair(int64_t)> load_;
  int64_t rows_, cols_, scene_, cached_ = 0;
  std::vector<CapturePair> cache_;
  torch::Tensor mix_;  // {4,3} float32, or undefined: none
};

constexpr int64_t kNoisePairs = 64;

// The normal equations of one step of (2), Y_i ~ F Z_i + s_i M (F {4,m,N}, Z_i {4,N,k}, M {4,m,k}),
// accumulated over the pairs.
struct Sums {
  torch::Tensor A, B, Sz;      // sum Z Z^T {4,N,N}, sum Y Z^T {4,m,N}, sum s Z {4,N,k}; float64
  torch::Tensor Sy, S2, norm;  // sum s Y {4,m,k}, sum s^2 {4}, sum ||Y||^2 {4}
};

// Each pair's scene split into its sum s {4} and its zero-mean rest Xz {4,N,N}, eq. (2).
std::pair<torch::Tensor, torch::Tensor> split_scene(const torch::Tensor& X) {
  const auto s = X.sum({1, 2});
  return {s, X - (s / static_cast<double>(X.size(1) * X.size(2))).view({4, 1, 1})};
}

// `design(pair)` gives the step's (Y_i, Z_i).
Sums accumulate(PairStream& pairs,
                const std::function<std::pair<torch::Tensor, torch::Tensor>(const CapturePair&)>& design) {
  Sums sums;
  for (int64_t i = 0; i < pairs.size(); ++i) {
    const auto pair = pairs.get(i);
    const auto [Y, Z] = design(pair);  // {4,m,k}, {4,N,k}
    const auto s = split_scene(pair.scene).first.view({4, 1, 1});
    const auto f64 = [](const torch::Tensor& t) { return t.to(torch::kFloat64); };
    const auto A = f64(torch::matmul(Z, Z.transpose(1, 2))), B = f64(torch::matmul(Y, Z.transpose(1, 2)));
    const auto Sz = f64(s * Z), Sy = f64(s * Y), S2 = f64(s.square().flatten()), norm = f64(Y.square().sum({1, 2}));
    if (i == 0) {
      sums.A = A;
      sums.B = B;
      sums.Sz = Sz;
      sums.Sy = Sy;
      sums.S2 = S2;
      sums.norm = norm;
    } else {
      sums.A += A, sums.B += B, sums.Sz += Sz, sums.Sy += Sy, sums.S2 += S2, sums.norm += norm;
    }
  }
  return sums;
}

// The model's residual over all pairs from the sums alone (F, M float64):
// sum ||Y - F Z - s M||^2 = |Y|^2 - 2<F,B> - 2<M,Sy> + <F A, F> + 2<F Sz, M> + S2 |M|^2.
torch::Tensor residual_energy(const Sums& t, const torch::Tensor& F, const torch::Tensor& M) {
  const auto dot = [](const torch::Tensor& a, const torch::Tensor& b) { return (a * b).sum({1, 2}); };
  return (t.norm - 2 * dot(F, t.B) - 2 * dot(M, t.Sy) + dot(torch::matmul(F, t.A), F) +
          2 * dot(torch::matmul(F, t.Sz), M) + t.S2 * M.square().sum({1, 2}))
      .clamp_min(0);
}

// The normal equations of one step with M eliminated (the header's formula): gram {4,N,N}, rhs {4,m,N}.
std::pair<torch::Tensor, torch::Tensor> reduced(const Sums& t) {
  const auto S2 = t.S2.clamp_min(1e-30).view({4, 1, 1});
  return {t.A - torch::matmul(t.Sz, t.Sz.transpose(1, 2)) / S2, t.B - torch::matmul(t.Sy, t.Sz.transpose(1, 2)) / S2};
}

// M for a given F: (Sy - F Sz) / S2.
torch::Tensor uniform_for(const Sums& t, const torch::Tensor& F) {
  return (t.Sy - torch::matmul(F, t.Sz)) / t.S2.clamp_min(1e-30).view({4, 1, 1});
}

// One free step: F and M minimising sum ||Y - F Z - s M||^2 + r ||F||^2, M eliminated (the header's
// formula). r per channel: `prior` = sigma^2 / mean(F^2) once the noise is known (the MAP estimate
// for Gaussian noise and a Gaussian prior on F's entries: directions the photographs hardly show,
// their fine detail, shrink to zero instead of fitting the noise); before, `ridge` times the Gram
// matrix's mean diagonal.
std::pair<torch::Tensor, torch::Tensor> solve_step(const Sums& t, double ridge, const torch::Tensor& prior) {
  const auto [gram, rhs] = reduced(t);
  const auto dim = gram.size(1);
  const auto mean_diag = gram.diagonal(0, 1, 2).mean(1).clamp_min(1e-30);
  const auto r = prior.defined() ? prior.to(torch::kFloat64) : ridge * mean_diag;
  const auto regularised = gram + r.view({4, 1, 1}) * torch::eye(dim, gram.options()).unsqueeze(0);
  const auto F = torch::linalg_solve(regularised, rhs.transpose(1, 2)).transpose(1, 2);  // gram is symmetric
  return {F, uniform_for(t, F)};
}

// One structured step (optics/shift_structure.hpp). The shift is searched on the first structured
// step, searched again on the next (the other factor is structured by then, which sharpens the
// search), then kept. The green channel gb, with the most light, chooses it for all four. (All four
// together found no more shifts on small noisy cameras, 10 of 16 either way, at four times the cost.)
struct StructuredFactor {
  double shift = 0;
  torch::Tensor profile;  // {4,L}: the warm start of the next step
  int steps = 0;
};

// noise_var {4}: the noise's variance per capture value, for the search's penalty (undefined: none).
// known: the shift when it is already known (fitted without a search), else 0.
std::pair<torch::Tensor, torch::Tensor> solve_structured_step(const Sums& t, const ShiftFitOptions& o,
                                                              const torch::Tensor& noise_var, double known,
                                                              StructuredFactor& state) {
  const auto [gram, rhs] = reduced(t);
  if (known != 0) {
    state.shift = known;
  } else if (state.steps < 2) {
    const auto g = gram.narrow(0, 1, 1), h = rhs.narrow(0, 1, 1);
    const double sigma2 = noise_var.defined() ? noise_var[1].item<double>() : 0.0;
    state.shift = search_shift(g, h, o, sigma2);
    state.profile = torch::Tensor();
  }
  ++state.steps;
  auto fit = fit_shift_factor(gram, rhs, state.shift, o, o.fit_iterations, state.profile);
  state.profile = fit.profile;
  return {fit.factor, uniform_for(t, fit.factor)};
}

// -J of a factor on a step's reduced normal equations, summed over the channels: the energy of the
// captures' coded part that it explains.
double explained(const std::pair<torch::Tensor, torch::Tensor>& normal, const torch::Tensor& F) {
  const auto& [gram, rhs] = normal;
  return (2 * (F * rhs).sum() - (torch::matmul(F, gram) * F).sum()).item<double>();
}

// A structured fit's share of the coded energy a free fit explains, each less what its parameters
// would fit of the noise alone (sigma^2 each, Akaike's correction). Parameters per channel: free
// m N, structured the profile's samples; sigma2 summed over the channels like the energies.
double penalised_share(double shaped, double shaped_params, double free, double free_params, double sigma2) {
  return (shaped - sigma2 * shaped_params) / std::max(1e-300, free - sigma2 * free_params);
}

// One axis's structured factor against the free one on the same step's sums (the other factor
// structured by then).
double axis_explains(const Sums& t, const torch::Tensor& shaped, int64_t profile_samples, double ridge,
                     const torch::Tensor& prior, const torch::Tensor& noise_var) {
  const auto free = solve_step(t, ridge, prior).first;
  const auto normal = reduced(t);
  const double sigma2 = noise_var.defined() ? noise_var.sum().item<double>() : 0.0;
  return penalised_share(explained(normal, shaped), static_cast<double>(profile_samples), explained(normal, free),
                         static_cast<double>(free.size(1) * free.size(2)), sigma2);
}

// The residual energy {4} of the model with no coded part (M alone): what the coded part starts from.
torch::Tensor uniform_only_energy(const Sums& t) {
  return (t.norm - t.Sy.square().sum({1, 2}) / t.S2.clamp_min(1e-30)).clamp_min(0);
}

// A searched shift in the outermost step of the coarse grid, at either end of the range: the cost
// still fell toward the range's edge, so no minimum was found inside it. From a few pairs of a camera
// whose shadow does not move that axis's way, the search drifts to the largest shift (whose longer
// profile fits more noise) and its share passed the verdict (issue 113): such a shift is no finding.
bool at_search_edge(double shift, const ShiftFitOptions& o) {
  const double a = std::abs(shift);
  return a * (1 + o.grid_step) > o.max_shift || a < o.min_shift * (1 + o.grid_step);
}

// The free model the structure is judged against (the header's verdict), kept to return to.
struct FreeModel {
  torch::Tensor P, Q, M, mix;
  torch::Tensor energy;        // {4} its residual energy over the pairs
  torch::Tensor uniform_only;  // {4} the same pass's residual energy of M alone
};

// The structured model's share of the coded energy the free one explains; sigma^2 is the free
// model's residual per pixel (the noise, as near as the pairs tell).
double structure_share(const FreeModel& free, const torch::Tensor& uniform_only, const torch::Tensor& energy,
                       double structured_params, double pixels) {
  const double free_params = static_cast<double>((free.P.size(1) + free.Q.size(1)) * free.P.size(2));
  return penalised_share((uniform_only - energy).sum().item<double>(), structured_params,
                         (free.uniform_only - free.energy).sum().item<double>(), free_params,
                         free.energy.sum().item<double>() / pixels);
}

// The mix step (the header's): each plane's shares of the primaries for fixed P {4,m,N}, Q {4,k,N},
// M {4,m,k}, by least squares over the first `count` pairs. Each row is scaled to sum 1 and P and M
// by the row's sum, so that the model is the least-squares one. A plane whose system is singular or
// whose shares do not sum to a positive number keeps its previous row.
torch::Tensor solve_mix(PairStream& pairs, int64_t count, torch::Tensor& P, const torch::Tensor& Q, torch::Tensor& M,
                        const torch::Tensor& previous) {
  auto gram = torch::zeros({4, 3, 3}, torch::kFloat64), rhs = torch::zeros({4, 3}, torch::kFloat64);
  for (int64_t i = 0; i < std::min(count, pairs.size()); ++i) {
    const auto pair = pairs.get_unmixed(i);
    const auto X = primaries(pair.scene);  // {3,N,N}
    const auto s = X.sum({1, 2});          // {3}
    const auto Xz = X - (s / static_cast<double>(X.size(1) * X.size(2))).view({3, 1, 1});
    // D[c][k] = P_c Xz_k Q_c^T + s_k M_c  {4,3,m,k}
    const auto coded = torch::matmul(torch::matmul(P.unsqueeze(1), Xz.unsqueeze(0)), Q.transpose(1, 2).unsqueeze(1));
    const auto D = (coded + s.view({1, 3, 1, 1}) * M.unsqueeze(1)).flatten(2).to(torch::kFloat64);  // {4,3,mk}
    gram += torch::matmul(D, D.transpose(1, 2));
    rhs += torch::matmul(D, pair.meas.flatten(1).to(torch::kFloat64).unsqueeze(2)).squeeze(2);
  }
  auto mix = previous.clone();
  for (int64_t c = 0; c < 4; ++c) {
    if (torch::linalg_matrix_rank(gram[c]).item<int64_t>() < 3) continue;
    const auto row = torch::linalg_solve(gram[c], rhs[c]);
    const double sum = row.sum().item<double>();
    if (!std::isfinite(sum) || sum <= 0) continue;
    mix[c] = row / sum;
    P[c] *= sum;
    M[c] *= sum;
  }
  return mix;
}

// P X Q^T is unchanged by P*k, Q/k: each channel's factors are given equal norms.
void balance(torch::Tensor& P, torch::Tensor& Q) {
  const auto k = (Q.flatten(1).norm(2, 1) / P.flatten(1).norm(2, 1).clamp_min(1e-30)).sqrt().view({4, 1, 1});
  P = P * k;
  Q = Q / k;
}

// The noise model and the camera fit's thresholds (optics/camera_fit.hpp fit_noise_model), on the
// first pairs. The residual against the shown scene, fitted before, holds the calibration's whole
// error, which grows with the light and tilted the line (135 of 150 dim captures of the camera itself
// flagged); outside the span only part of that error is left, and the pairs' own fits (0.65-1.2 with
// a 100-pair calibration) set the threshold.
void fit_noise_outside_span(PairStream& pairs, const torch::Tensor& P, const torch::Tensor& Q,
                            DatasetCalibration& out) {
  std::vector<NoiseSample> samples;
  for (int64_t i = 0; i < std::min<int64_t>(pairs.size(), kNoisePairs); ++i) {
    const auto pair = pairs.get(i);
    samples.push_back({pair.meas, pair.level, pair.saturated});
  }
  const auto noise = fit_noise_model(samples, P, Q);
  if (!noise.found) return;
  out.noise_gain = noise.noise_gain;
  out.noise_floor = noise.noise_floor;
  out.dark = noise.dark;
  out.fit_threshold = noise.fit_threshold;
  out.leak_threshold = noise.leak_threshold;
}

// Pairs that cannot identify a calibration are named before the first solve, which would otherwise
// be singular (flat scenes: no zero-mean part, Z = 0) or fit a calibration of zeros (captures with
// nothing in them after centring: a lens cap, a dark frame).
void require_signal(const Sums& first, int64_t count, int64_t pixels, int64_t scene) {
  const double capture_power = first.norm.sum().item<double>() / static_cast<double>(4 * count * pixels);
  require_option(capture_power > 1e-14, "calibrate.dataset",
                 "the captures carry no signal after centring (all " + std::to_string(count) +
                     " flat: a lens cap, a dark frame, or the display off?)");
  // sum over the pairs of ||Xz Q^T||^2 (about ||Xz||^2: Q's rows have unit norm on average) against
  // the scenes' mean light, sum s^2 / N^2 = ||mean||^2: float rounding leaves ~1e-14 of it in a flat
  // scene's Xz.
  const auto scene_power = first.A.diagonal(0, 1, 2).sum(1);  // {4}
  const auto mean_power = first.S2 / static_cast<double>(scene * scene);
  require_option((scene_power > 1e-9 * mean_power).all().item<bool>() && scene_power.max().item<double>() > 0,
                 "calibrate.dataset",
                 "the photographs have no contrast in some colour channel (all " + std::to_string(count) +
                     " flat: one grey level each), so nothing identifies the camera; show photographs");
}

void require_valid(const DatasetCalibrationOptions& o, int64_t count) {
  require_option(count >= 1, "calibrate.dataset", "no pairs to calibrate from");
  require_option(o.iterations >= 1 && o.ridge >= 0 && o.tolerance >= 0, "calibrate.dataset",
                 "iterations >= 1, ridge >= 0 and tolerance >= 0 are needed");
  require_option(o.structure == FactorStructure::Free || o.iterations >= o.free_passes + 2, "calibrate.dataset",
                 "the shift structure is judged after the free passes and two shift searches per axis: iterations >= "
                 "free_passes + 2 are needed");
}

// The progress bar's status of a pass: the relative residual and what the factors are.
std::string fit_status(double total, bool rejected, const StructuredFactor& p, const StructuredFactor& q) {
  std::ostringstream status;
  status << "residual " << std::setprecision(4) << total;
  if (rejected)
    status << ", free factors";
  else if (p.steps > 0)
    status << ", shifts " << p.shift << " " << q.shift;
  return status.str();
}

}  // namespace

torch::Tensor scene_through_mix(const torch::Tensor& scene, const torch::Tensor& mix) {
  return torch::einsum("ck,khw->chw", {mix.to(scene.dtype()), primaries(scene)});
}

DatasetCalibration calibrate_from_pairs(int64_t count, const std::function<CapturePair(int64_t)>& load, int64_t rows,
                                        int64_t cols, int64_t scene, const DatasetCalibrationOptions& o) {
  require_valid(o, count);
  PairStream pairs(count, load, rows, cols, scene, o.cache_bytes);
  auto gen = at::detail::createCPUGenerator(o.seed);
  auto Q = at::randn({4, cols, scene}, gen) / std::sqrt(static_cast<double>(cols));  // a random start
  torch::Tensor P, M;                                                                // float32 for the passes
  DatasetCalibration result;
  result.pairs = count;
  Progress progress("calibrate", o.iterations, o.progress);
  double last = std::numeric_limits<double>::infinity();
  // P-step: Y ~ P (Xz Q^T) + s M.   Q-step: Y^T ~ Q (P Xz)^T + s M^T.
  auto mix = unmixed();  // {4,3}
  const auto p_design = [&](const CapturePair& p) {
    return std::make_pair(p.meas, torch::matmul(split_scene(p.scene).second, Q.transpose(1, 2)));
  };
  const auto q_design = [&](const CapturePair& p) {
    return std::make_pair(p.meas.transpose(1, 2), torch::matmul(P, split_scene(p.scene).second).transpose(1, 2));
  };
  torch::Tensor noise_var;  // {4} the residual per pixel: the noise, once a model exists
  const double pixels = static_cast<double>(count * rows * cols);
  const auto prior_for = [&](const torch::Tensor& F) {
    return noise_var.defined() ? noise_var / F.to(torch::kFloat64).square().mean({1, 2}).clamp_min(1e-30)
                               : torch::Tensor();
  };
  StructuredFactor p_shape, q_shape;
  // Scenes made from RGB photographs show gb and gr the same green; four unrelated planes (a
  // synthetic camera) have no primaries to mix.
  const auto first = pairs.get_unmixed(0).scene;
  const bool identify_mix = o.identify_mix && torch::equal(first[1], first[2]);
  FreeModel free;       // the model before the first structured step, once there is one
  bool judged = false;  // the structure's verdict is given
  for (int it = 0; it <= o.iterations; ++it) {
    const bool structured = o.structure == FactorStructure::Shift && it >= o.free_passes && !result.structure_rejected;
    // The P-step's pass also scores the current (P, Q, M).
    const auto sums = accumulate(pairs, p_design);
    if (it == 0) require_signal(sums, count, rows * cols, scene);
    if (P.defined()) {
      auto energy = residual_energy(sums, P.to(torch::kFloat64), M.to(torch::kFloat64));
      if (structured && p_shape.steps == 0) {  // the free model, before the structure is tried
        free = {P, Q, M, mix, energy, uniform_only_energy(sums)};
      } else if (structured && !judged && (p_shape.steps >= 2 || it == o.iterations) && free.P.defined()) {
        // Both factors have searched their shift twice: the verdict on the whole structured model.
        judged = true;
        const double samples = static_cast<double>(p_shape.profile.size(1) + q_shape.profile.size(1));
        result.structure_explains = structure_share(free, uniform_only_energy(sums), energy, samples, pixels);
        result.shift_at_edge = {at_search_edge(p_shape.shift, o.shift), at_search_edge(q_shape.shift, o.shift)};
        const bool edge = result.shift_at_edge[0] || result.shift_at_edge[1];
        if (o.judge_structure && (result.structure_explains < kStructureExplainsAtLeast || edge)) {
          result.structure_rejected = true;  // back to the free model, and free steps from here on
          P = free.P, Q = free.Q, M = free.M, mix = free.mix;
          if (identify_mix) pairs.set_mix(mix);
          energy = free.energy;
          last = std::numeric_limits<double>::infinity();
        }
      }
      noise_var = energy / pixels;
      const auto rel = (energy / sums.norm.clamp_min(1e-30)).sqrt();
      for (int c = 0; c < 4; ++c) result.residual[c] = rel[c].item<double>();
      const double total = std::sqrt(energy.sum().item<double>() / std::max(1e-30, sums.norm.sum().item<double>()));
      progress.set_status(fit_status(total, result.structure_rejected, p_shape, q_shape));
      progress.tick();
      result.iterations = it;
      if (last - total < o.tolerance * last || it == o.iterations) break;
      last = total;
    }
    const bool shaped = structured && !result.structure_rejected;
    // A step that changes the model's form (free to structured, a new shift) is not compared with the last.
    if (shaped && p_shape.steps < 2) last = std::numeric_limits<double>::infinity();
    auto [F, Mp] = shaped ? solve_structured_step(sums, o.shift, noise_var, o.shifts[0], p_shape)
                          : solve_step(sums, o.ridge, P.defined() ? prior_for(P) : torch::Tensor());
    if (shaped && p_shape.steps == 2)  // the row shift's second search, with Q structured
      result.axis_explains[0] = axis_explains(sums, F, p_shape.profile.size(1), o.ridge, prior_for(P), noise_var);
    P = F.to(torch::kFloat32);
    M = Mp.to(torch::kFloat32);
    const auto qsums = accumulate(pairs, q_design);
    auto [G, Mq] = shaped ? solve_structured_step(qsums, o.shift, noise_var, o.shifts[1], q_shape)
                          : solve_step(qsums, o.ridge, prior_for(Q));
    if (shaped && q_shape.steps == 2)  // the column shift's, with P structured
      result.axis_explains[1] = axis_explains(qsums, G, q_shape.profile.size(1), o.ridge, prior_for(Q), noise_var);
    Q = G.to(torch::kFloat32);
    M = Mq.transpose(1, 2).to(torch::kFloat32);
    balance(P, Q);
    if (identify_mix && it + 1 >= o.free_passes) {
      mix = solve_mix(pairs, o.mix_pairs, P, Q, M, mix);
      pairs.set_mix(mix);
    }
  }
  result.searched_shifts = {p_shape.shift, q_shape.shift};
  result.shift_rows = result.structure_rejected ? 0 : p_shape.shift;
  result.shift_cols = result.structure_rejected ? 0 : q_shape.shift;
  progress.finish();
  fit_noise_outside_span(pairs, P, Q, result);
  result.calib.P = P.to(torch::kFloat64);
  result.calib.Q = Q.to(torch::kFloat64);
  result.uniform_response = M;
  if (identify_mix) result.colour_mix = mix;
  return result;
}

}  // namespace flatnet
