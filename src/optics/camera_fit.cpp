#include "optics/camera_fit.hpp"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <limits>
#include <sstream>
#include <vector>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/raw.hpp"

namespace flatnet {

namespace {

// The largest singular value squared of each {h,w} matrix, by power iteration on R^T R (the
// open part's rank-1 light dominates it when present; otherwise the noise's largest). Plain loops on
// one thread: 30 pairs of matrix-vector products are far too small to share between threads, and
// LibTorch's parallel batched products of one column cost a scheduler slice each on a busy machine.
torch::Tensor top_singular_squared(const torch::Tensor& R) {
  const auto Rc = R.to(torch::kFloat64).contiguous();
  const int64_t channels = Rc.size(0), h = Rc.size(1), w = Rc.size(2);
  auto out = torch::zeros({channels}, torch::kFloat64);
  std::vector<double> v(static_cast<size_t>(w)), u(static_cast<size_t>(h)), next(static_cast<size_t>(w));
  for (int64_t c = 0; c < channels; ++c) {
    const double* m = Rc.data_ptr<double>() + c * h * w;
    std::fill(v.begin(), v.end(), 1.0 / std::sqrt(static_cast<double>(w)));
    double norm2 = 0;
    for (int it = 0; it < 30; ++it) {
      for (int64_t i = 0; i < h; ++i) {  // u = R v
        double acc = 0;
        for (int64_t j = 0; j < w; ++j) acc += m[i * w + j] * v[static_cast<size_t>(j)];
        u[static_cast<size_t>(i)] = acc;
      }
      std::fill(next.begin(), next.end(), 0.0);  // next = R^T u
      for (int64_t i = 0; i < h; ++i)
        for (int64_t j = 0; j < w; ++j) next[static_cast<size_t>(j)] += m[i * w + j] * u[static_cast<size_t>(i)];
      double vw = 0, nn = 0;
      for (int64_t j = 0; j < w; ++j)
        vw += v[static_cast<size_t>(j)] * next[static_cast<size_t>(j)],
            nn += next[static_cast<size_t>(j)] * next[static_cast<size_t>(j)];
      norm2 = vw;  // v^T R^T R v, v of unit length
      if (nn <= 0) break;
      const double inv = 1 / std::sqrt(nn);
      for (int64_t j = 0; j < w; ++j) v[static_cast<size_t>(j)] = next[static_cast<size_t>(j)] * inv;
    }
    out[c] = norm2;
  }
  return out;
}

// The near-twin test's rank: the largest singular value is compared with the 41st, inside the noise's
// bulk for these block sizes (a coded scene's leak is a few strong directions, fewer than 41).
constexpr int64_t kLeakRank = 40;
// Below this many noise dimensions in a block the 41st singular value is too near the edge to be a
// stable reference (the tiny test cameras): the leak is not measured there.
constexpr int64_t kLeakMinDimensions = 6 * kLeakRank;

// The leading eigenvector of a symmetric positive semi-definite G {n,n} float64, by power iteration
// from a fixed pseudo-random start (a constant start can be orthogonal to it in centred planes). It
// stops when the Rayleigh quotient settles; where the top two eigenvalues are close (no open light:
// the top is noise's), any vector of the top pair does, since noise's top is then what is set aside.
torch::Tensor leading_eigenvector(const torch::Tensor& G) {
  auto gen = at::detail::createCPUGenerator(7);
  auto v = torch::randn({G.size(0)}, gen, G.options());
  v = v / v.norm();
  double previous = 0;
  for (int it = 0; it < 40; ++it) {
    const auto next = torch::mv(G, v);
    const double norm = next.norm().item<double>();
    if (!(norm > 0)) break;
    v = next / norm;
    if (std::abs(norm - previous) <= 1e-6 * norm) break;
    previous = norm;
  }
  return v;
}

// (I - v v^T) G (I - v v^T): the Gram of a matrix with its strongest rank-1 component set aside.
torch::Tensor without_direction(const torch::Tensor& G, const torch::Tensor& v) {
  const auto Gv = torch::mv(G, v);
  const auto vGv = torch::dot(v, Gv);
  return G - torch::outer(v, Gv) - torch::outer(Gv, v) + vGv * torch::outer(v, v);
}

// Grams {4,n,n} of the four planes' blocks -> sqrt(lambda_1 / lambda_41) of their sum (the blocks
// stacked), each plane's leading direction set aside first (the open part's light, rank 1 per plane).
double stacked_spike(const torch::Tensor& grams) {
  torch::Tensor sum = torch::zeros({grams.size(1), grams.size(2)}, grams.options());
  for (int64_t c = 0; c < grams.size(0); ++c) sum += without_direction(grams[c], leading_eigenvector(grams[c]));
  const auto eig = torch::linalg_eigvalsh(sum);  // ascending
  const int64_t n = eig.size(0);
  const double top = eig[n - 1].item<double>(), bulk = eig[n - 1 - kLeakRank].item<double>();
  return bulk > 0 ? std::sqrt(top / bulk) : std::numeric_limits<double>::infinity();
}

bool leak_measurable(int64_t h, int64_t w, int64_t n) {
  return std::min(h, w) - n - 1 >= kLeakMinDimensions && n > kLeakRank;
}

}  // namespace

double coded_leak(const torch::Tensor& planes, const torch::Tensor& U, const torch::Tensor& V) {
  torch::NoGradGuard no_grad;
  if (!leak_measurable(U.size(1), V.size(1), U.size(2))) return std::nan("");
  // Double-centred whatever the camera's centring: rows, columns and the level are no coded scene.
  const auto Y = (planes - planes.mean(-1, true) - planes.mean(-2, true) + planes.mean({-2, -1}, true))
                     .to(torch::kFloat32);  // {4,h,w}
  const auto Ut = U.transpose(1, 2), Vt = V.transpose(1, 2);
  const auto YV = torch::matmul(Y, V);                          // {4,h,N}
  const auto C = YV - torch::matmul(U, torch::matmul(Ut, YV));  // {4,h,N}: (I - U U^T) Y V
  const auto UY = torch::matmul(Ut, Y);                         // {4,N,w}
  const auto B = UY - torch::matmul(torch::matmul(UY, V), Vt);  // {4,N,w}: U^T Y (I - V V^T)
  // The planes' C side by side {h,4N} has the Gram sum_c C_c C_c^T; their B stacked {4N,w}, sum_c B_c^T B_c.
  const auto gram_C = torch::matmul(C, C.transpose(1, 2)).to(torch::kFloat64);  // {4,h,h}
  const auto gram_B = torch::matmul(B.transpose(1, 2), B).to(torch::kFloat64);  // {4,w,w}
  return std::max(stacked_spike(gram_C), stacked_spike(gram_B));
}

double noise_leak(const torch::Tensor& U, const torch::Tensor& V, int draws) {
  auto gen = at::detail::createCPUGenerator(2026);
  double largest = 0;
  for (int d = 0; d < draws; ++d)
    largest = std::max(largest, coded_leak(torch::randn({U.size(0), U.size(1), V.size(1)}, gen, U.options()), U, V));
  return largest;
}

torch::Tensor at_full_scale(const torch::Tensor& window, int adc_bits) {
  const double top = static_cast<double>(((1 << adc_bits) - 1) * (1 << (16 - adc_bits))) / 65535.0;
  return window >= static_cast<float>(top - 0.5 / 65535.0);
}

torch::Tensor unexplained_energy(const torch::Tensor& Y, const torch::Tensor& U, const torch::Tensor& V) {
  const auto inside = torch::matmul(torch::matmul(U, torch::matmul(torch::matmul(U.transpose(1, 2), Y), V)),
                                    V.transpose(1, 2));  // {4,h,w}: U U^T Y V V^T
  const auto R = (Y - inside).to(torch::kFloat64);
  return R.square().sum({1, 2}) - top_singular_squared(R);
}

double outside_share(int64_t h, int64_t w, int64_t n) {
  const double hd = static_cast<double>(h), wd = static_cast<double>(w), nd = static_cast<double>(n);
  const double dof = (hd - 1) * (wd - 1) - nd * nd;
  return (dof - std::pow(std::sqrt(hd - 1) + std::sqrt(wd - 1), 2)) / (hd * wd);
}

bool camera_fit_measurable(int64_t h, int64_t w, int64_t n) {
  const double dof =
      static_cast<double>(h - 1) * static_cast<double>(w - 1) - static_cast<double>(n) * static_cast<double>(n);
  return dof > 1000;
}

CameraFit::CameraFit(const Calibration& calib, const CameraConfig& camera) : camera_(camera) {
  require(camera.knows_noise(), camera.name,
          "this camera has no noise model (noise_gain, noise_floor, dark); `flatnet calibrate --dataset` measures it");
  require(calib.P.dim() == 3 && calib.P.size(0) == 4 && calib.P.size(1) == camera.raw.crop[2] && calib.Q.dim() == 3 &&
              calib.Q.size(1) == camera.raw.crop[3] && calib.P.size(2) == calib.Q.size(2),
          camera.name, "the calibration does not match the camera's crop");
  // Orthonormal bases of P's and Q's column spaces (reduced QR, in float64 for the small columns).
  U_ = std::get<0>(torch::linalg_qr(calib.P.to(torch::kFloat64))).to(torch::kFloat32).contiguous();
  V_ = std::get<0>(torch::linalg_qr(calib.Q.to(torch::kFloat64))).to(torch::kFloat32).contiguous();
  if (calib.fixed_light.defined()) fixed_light_ = calib.fixed_light.to(torch::kFloat32).contiguous();
  const double h = static_cast<double>(U_.size(1)), w = static_cast<double>(V_.size(1));
  const double n = static_cast<double>(U_.size(2));
  const double dof = (h - 1) * (w - 1) - n * n;
  require(camera_fit_measurable(U_.size(1), V_.size(1), U_.size(2)), camera.name,
          "the capture window is too small beside the scene to test a capture's fit");
  // Chance alone: the pooled energy of 4 * dof noise terms has relative deviation sqrt(2 / (4 dof)).
  // Six deviations, and 1 % for calibration error and the noise model's own.
  threshold_ = std::max(1 + 6 * std::sqrt(2 / (4 * dof)) + 0.01, camera.fit_threshold);
  outside_share_ = outside_share(U_.size(1), V_.size(1), U_.size(2));
  // Noise alone, with a 10 % margin (noise spreads over 1.17-1.20 at 500x620 and N 256; a near twin's
  // coded scene gives 1.3-3); a calibration estimated from pairs leaves its own error's structure
  // outside its spans, and its camera file carries the threshold its pairs need (calibrate --dataset).
  if (leak_measurable(U_.size(1), V_.size(1), U_.size(2)))
    leak_threshold_ = std::max(1.1 * noise_leak(U_, V_), camera.leak_threshold);
}

double CameraFit::excess(const CameraFitResult& r) const {
  const double by_leak = leak_threshold_ > 0 && std::isfinite(r.leak) ? r.leak / leak_threshold_ : 0;
  return std::max(r.fit / threshold_, by_leak);
}

std::string CameraFit::verdict(const CameraFitResult& r) const {
  std::ostringstream text;
  text << std::setprecision(3);
  const bool fit_fails = !(r.fit <= threshold_);
  if (fit_fails || r.leak_matches) text << "fit " << r.fit << " against <= " << threshold_;  // or within both
  if (!r.leak_matches)
    text << (fit_fails ? ", " : "") << "coded leak " << r.leak << " against <= " << leak_threshold_
         << ": a coded scene outside the calibration's spans, as from another mask on this sensor";
  return text.str();
}

CameraFitResult CameraFit::measure(const torch::Tensor& raw_unit) const {
  torch::NoGradGuard no_grad;
  const auto& g = camera_.raw;
  const auto window = raw_window(raw_unit, g);  // {4,h,w}: the light each pixel read
  // The separable model's planes, less the light the calibration says every capture holds.
  const auto Y = without_fixed_light(without_level(double_centre(window, g.centring), g.centring), fixed_light_);
  const auto unexplained = unexplained_energy(Y, U_, V_).sum();
  // The noise model, pixel by pixel: clipped pixels carry no noise.
  const int bits = g.adc_bits;
  const auto saturated = at_full_scale(window, bits);
  // The ADC's rounding is noise every pixel has, whatever the fitted floor says: (1 LSB)^2 / 12.
  const double lsb = 1.0 / static_cast<double>((1 << bits) - 1);
  const double floor = std::max(camera_.noise_floor, lsb * lsb / 12);
  const auto var = torch::where(saturated, torch::zeros_like(window),
                                (window - camera_.dark).clamp_min(0) * camera_.noise_gain + floor)
                       .to(torch::kFloat64);
  const double expected = var.sum().item<double>() * outside_share_;
  CameraFitResult r;
  r.fit = unexplained.item<double>() / std::max(1e-30, expected);
  r.saturated = saturated.to(torch::kFloat32).mean().item<double>();
  // A capture with clipped pixels breaks the noise model (a clipped pixel reads no noise, and the
  // clipping itself is no P X Q^T): beyond 1 % of the window it cannot be judged, and is not flagged.
  r.judged = r.saturated <= kMaxSaturatedShare;
  // The leak of an unjudged capture would be its clipping's: not measured (nan), not flagged.
  const bool leak_tested = leak_threshold_ > 0 && r.judged;
  r.leak = leak_tested ? coded_leak(Y, U_, V_) : std::nan("");
  r.leak_matches = !leak_tested || r.leak <= leak_threshold_;
  r.matches = !r.judged || (std::isfinite(r.fit) && r.fit <= threshold_ && r.leak_matches);
  return r;
}

NoiseModelFit fit_noise_model(const std::vector<NoiseSample>& samples, const torch::Tensor& P, const torch::Tensor& Q) {
  torch::NoGradGuard no_grad;
  NoiseModelFit out;
  const auto U = std::get<0>(torch::linalg_qr(P.to(torch::kFloat64))).to(torch::kFloat32);
  const auto V = std::get<0>(torch::linalg_qr(Q.to(torch::kFloat64))).to(torch::kFloat32);
  const int64_t h = U.size(1), w = V.size(1);
  const double per_pixel = outside_share(h, w, U.size(2)) * static_cast<double>(h * w);
  std::vector<double> levels, energies;  // per plane
  double largest_leak = 0;  // the captures' own near-twin statistic: an estimated calibration's error is structured too
  for (const auto& sample : samples) {
    if (!sample.level.defined()) return out;
    // Clipped pixels are no P X Q^T: a saturated capture's leak is the clipping's (2.5-2.8 measured on
    // the reference camera's), and the camera fit does not judge such captures either.
    if (sample.saturated <= kMaxSaturatedShare) largest_leak = std::max(largest_leak, coded_leak(sample.meas, U, V));
    const auto outside = unexplained_energy(sample.meas, U, V) / per_pixel;  // {4}
    const auto level = sample.level.to(torch::kFloat64).flatten();
    for (int c = 0; c < 4; ++c)
      levels.push_back(level[c].item<double>()), energies.push_back(outside[c].item<double>());
  }
  if (energies.size() < 8) return out;
  const auto n = static_cast<int64_t>(energies.size());
  auto A = torch::ones({n, 2}, torch::kFloat64);
  A.select(1, 0).copy_(torch::tensor(levels, torch::kFloat64));
  const auto x = std::get<0>(torch::linalg_lstsq(A, torch::tensor(energies, torch::kFloat64).unsqueeze(1))).flatten();
  const double gain = x[0].item<double>(), offset = x[1].item<double>();
  if (!(gain > 0) || !std::isfinite(gain) || !std::isfinite(offset)) return out;
  out.found = true;
  out.noise_gain = gain;
  out.noise_floor = std::max(0.0, offset);
  out.dark = offset < 0 ? -offset / gain : 0.0;
  // Each capture's fit as the camera fit computes it (four planes pooled, the level per plane).
  for (size_t i = 0; i + 4 <= energies.size(); i += 4) {
    double seen = 0, expected = 0;
    for (size_t c = i; c < i + 4; ++c)
      seen += energies[c], expected += std::max(0.0, levels[c] - out.dark) * gain + out.noise_floor;
    out.fits.push_back(seen / std::max(expected, 1e-30));
  }
  double mean = 0, square = 0;
  for (double f : out.fits) mean += f, square += f * f;
  mean /= static_cast<double>(out.fits.size());
  const double deviation = std::sqrt(std::max(0.0, square / static_cast<double>(out.fits.size()) - mean * mean));
  const double largest = *std::max_element(out.fits.begin(), out.fits.end());
  out.fit_threshold = std::max({1.0, 1.1 * largest, mean + 5 * deviation});
  if (largest_leak > 0) out.leak_threshold = std::max(1.0, 1.1 * largest_leak);
  return out;
}

BatchFit judge_batch(const CameraFit& fit, const std::vector<CameraFitResult>& results) {
  std::vector<double> excess;
  for (const auto& r : results)
    if (r.judged) {
      const double e = fit.excess(r);
      excess.push_back(std::isnan(e) ? std::numeric_limits<double>::infinity() : e);  // nan: no fit at all
    }
  BatchFit b;
  b.judged = static_cast<int64_t>(excess.size());
  if (excess.empty()) return b;
  const auto lower_median = excess.begin() + (excess.size() - 1) / 2;
  std::nth_element(excess.begin(), lower_median, excess.end());
  b.median_excess = *lower_median;
  b.foreign = b.judged >= kMinBatchJudged && b.median_excess > 1;
  return b;
}

}  // namespace flatnet
