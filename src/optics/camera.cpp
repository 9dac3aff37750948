#include "optics/camera.hpp"

#include <cmath>
#include <iostream>

#include "optics/bench.hpp"
#include "optics/shift_structure.hpp"

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "io/raw.hpp"

namespace flatnet {

using torch::indexing::Slice;

const std::array<const char*, 4> kChannelNames = {"b", "gb", "gr", "r"};

int channel_index(const std::string& name) {
  for (int c = 0; c < 4; ++c)
    if (name == kChannelNames[c]) return c;
  throw Error("config: model.inversion.channel must be b, gb, gr or r, got '" + name + "'");
}

Rig load_rig(const std::filesystem::path& path) {
  MatReader mat(path);
  Rig rig;
  const auto phil0 = mat.read("PhiL_b");
  const auto phir0 = mat.read("PhiR_b");
  require(phil0.dim() == 2 && phir0.dim() == 2 && phil0.size(1) == phir0.size(1), path,
          "PhiL_b and PhiR_b must be matrices with the same number of columns (scene size)");
  const auto H = phil0.size(0), W = phir0.size(0), N = phil0.size(1);
  std::vector<torch::Tensor> L, R, G;
  for (const char* c : kChannelNames) {
    L.push_back(mat.read(std::string("PhiL_") + c, {H, N}));
    R.push_back(mat.read(std::string("PhiR_") + c, {W, N}));
    G.push_back(torch::tensor(mat.read_scalar(std::string("gain_") + c), torch::kFloat64));
  }
  rig.phil = torch::stack(L).to(torch::kFloat32);
  rig.phir = torch::stack(R).to(torch::kFloat32);
  rig.gain = torch::stack(G).to(torch::kFloat32);
  rig.vig_rows = mat.read("vig_rows", {H}).to(torch::kFloat32);
  rig.vig_cols = mat.read("vig_cols", {W}).to(torch::kFloat32);
  for (const auto& [name, t] : std::vector<std::pair<std::string, torch::Tensor>>{{"PhiL_*", rig.phil},
                                                                                  {"PhiR_*", rig.phir},
                                                                                  {"gain_*", rig.gain},
                                                                                  {"vig_rows", rig.vig_rows},
                                                                                  {"vig_cols", rig.vig_cols}})
    require(torch::isfinite(t).all().item<bool>(), path, name + " contains NaN or Inf");
  rig.full_well = mat.read_scalar("full_well");
  rig.read_noise = mat.read_scalar("read_noise");
  rig.dark = mat.read_scalar("dark");
  rig.adc_bits = static_cast<int>(mat.read_scalar("adc_bits"));
  require(rig.full_well > 0 && rig.read_noise >= 0 && rig.adc_bits >= 1 && rig.adc_bits <= 16, path,
          "implausible sensor constants (full_well > 0, read_noise >= 0, 1 <= adc_bits <= 16)");
  return rig;
}

namespace {

// The share of white noise's variance that survives preprocessing's rotation (io/raw.hpp
// rotate_planes): each output pixel is a bilinear mix of four, whose squared weights sum to
// ((1-fr)^2 + fr^2)((1-fc)^2 + fc^2), averaged over the window. FlatNet's prototype: 0.00174 rad turns
// the window's rows by up to a pixel, and keeps 0.46 of the variance. The noise model is measured on
// rotated captures, so a simulator adds noise before rotation at 1 / this of it.
double rotation_variance_kept(const RawGeometry& g) {
  if (g.rotation == 0.0) return 1.0;
  const auto f64 = torch::TensorOptions().dtype(torch::kFloat64);
  const auto r = torch::arange(g.crop[0], g.crop[0] + g.crop[2], f64).unsqueeze(1);
  const auto c = torch::arange(g.crop[1], g.crop[1] + g.crop[3], f64).unsqueeze(0);
  const auto src_r = std::sin(g.rotation) * c + std::cos(g.rotation) * r;
  const auto src_c = std::cos(g.rotation) * c - std::sin(g.rotation) * r;
  const auto fr = src_r - src_r.floor(), fc = src_c - src_c.floor();
  const auto kept = ((1 - fr).square() + fr.square()) * ((1 - fc).square() + fc.square());
  return kept.mean().item<double>();
}

}  // namespace

Rig calibration_rig(const Calibration& calib, const CameraConfig& camera) {
  const auto& g = camera.raw;
  const int64_t n = camera.scene_size, h = g.crop[2], w = g.crop[3];
  require(calib.P.dim() == 3 && calib.P.size(0) == 4 && calib.P.size(1) == h && calib.P.size(2) == n &&
              calib.Q.dim() == 3 && calib.Q.size(0) == 4 && calib.Q.size(1) == w && calib.Q.size(2) == n,
          camera.calibration, "does not match camera '" + printable(camera.name) + "' (its crop and scene size)");
  require(camera.knows_noise() && camera.open_light > 0, camera.name,
          "a camera simulated through its calibration needs its noise model and open_light (flatnet calibrate)");
  const double lsb = 1.0 / (std::pow(2.0, g.adc_bits) - 1);
  Rig rig;
  rig.phil = torch::zeros({4, g.plane_height(), n});
  rig.phir = torch::zeros({4, g.plane_width(), n});
  rig.phil.narrow(1, g.crop[0], h).copy_(calib.P);
  rig.phir.narrow(1, g.crop[1], w).copy_(calib.Q);
  if (calib.fixed_light.defined()) {
    rig.fixed_light = torch::zeros({4, g.plane_height(), g.plane_width()});
    rig.fixed_light.narrow(1, g.crop[0], h).narrow(2, g.crop[1], w).copy_(calib.fixed_light);
  }
  rig.gain = torch::ones({4});
  // expected_signal's open term is vig_rows vig_cols^T sum(X) = open_light * mean(X).
  const double vig = std::sqrt(camera.open_light) / static_cast<double>(n);
  rig.vig_rows = torch::full({g.plane_height()}, vig);
  rig.vig_cols = torch::full({g.plane_width()}, vig);
  // The noise model is what rotated planes show; before rotation the noise is 1 / kept stronger.
  const double kept = rotation_variance_kept(g);
  rig.full_well = kept / camera.noise_gain;
  rig.read_noise = rig.full_well * std::sqrt(std::max(0.0, camera.noise_floor / kept - lsb * lsb / 12));
  rig.dark = camera.dark;
  rig.adc_bits = g.adc_bits;
  return rig;
}

bool can_simulate(const CameraConfig& camera) {
  return !camera.rig.empty() || (camera.open_light > 0 && !camera.calibration.empty());
}

std::filesystem::path simulation_source(const CameraConfig& camera) {
  return camera.rig.empty() ? camera.calibration : camera.rig;
}

Rig load_camera_rig(const CameraConfig& camera) {
  if (camera.rig.empty() && camera.open_light > 0 && !camera.calibration.empty()) {
    std::cerr << "camera '" << printable(camera.name) << "' has no rig: simulated through its calibration\n";
    auto rig = calibration_rig(load_calibration(camera.calibration, camera), camera);
    rig.bench = camera.bench;
    rig.display_gamma = camera.display_gamma;
    return rig;
  }
  require(!camera.rig.empty(), camera.name,
          "this camera names no rig (rig.mat, its true response), and has no open_light to be simulated through "
          "its calibration");
  auto rig = load_rig(camera.rig);
  rig.bench = camera.bench;
  rig.display_gamma = camera.display_gamma;
  require(rig.scene_size() == camera.scene_size, camera.rig,
          "models a " + std::to_string(rig.scene_size()) + "-pixel scene, and camera '" + printable(camera.name) +
              "' says scene_size " + std::to_string(camera.scene_size));
  // The rig makes whole Bayer planes (raw / 2); the camera's crop must lie inside them.
  const auto rows = rig.phil.size(1), cols = rig.phir.size(1);
  const auto& crop = camera.raw.crop;
  require(crop[0] + crop[2] <= rows && crop[1] + crop[3] <= cols, camera.rig,
          "makes " + std::to_string(rows) + "x" + std::to_string(cols) + " planes, and camera '" +
              printable(camera.name) + "' crops rows " + std::to_string(crop[0]) + ".." +
              std::to_string(crop[0] + crop[2] - 1) + ", columns " + std::to_string(crop[1]) + ".." +
              std::to_string(crop[1] + crop[3] - 1));
  return rig;
}

torch::Tensor expected_signal(const Rig& rig, const torch::Tensor& scene_planes) {
  // scene_planes: {B,4,N,N} linear light
  auto X = scene_planes.to(torch::kFloat32);
  auto coded = torch::matmul(torch::matmul(rig.phil, X), rig.phir.transpose(1, 2));  // {B,4,h,w}
  auto open = torch::outer(rig.vig_rows, rig.vig_cols) * X.sum({-2, -1}).unsqueeze(-1).unsqueeze(-1);
  const auto signal = rig.gain.view({1, 4, 1, 1}) * (coded + open);
  return rig.fixed_light.defined() ? signal + rig.fixed_light : signal;
}

torch::Tensor photon_electrons(const torch::Tensor& mean, c10::optional<at::Generator> gen) {
  // LibTorch's Poisson sampler is serial (~0.1 s per 1.3 Mpixel frame). Above kExactPoissonBelow
  // electrons a Poisson count is Normal(mean, sqrt(mean)) to within its skewness 1/sqrt(mean) < 3%,
  // far below a 10-bit ADC step; below it (dark regions) it is sampled exactly.
  constexpr double kExactPoissonBelow = 1000.0;
  auto out = mean + torch::sqrt(mean) * at::normal(0.0, 1.0, mean.sizes(), gen, mean.options());
  auto low = mean < kExactPoissonBelow;
  if (low.any().item<bool>()) out.masked_scatter_(low, at::poisson(mean.masked_select(low), gen));
  return out;
}

torch::Tensor sensor_readout(const Rig& rig, const torch::Tensor& signal, bool noise,
                             c10::optional<at::Generator> gen) {
  // float32 throughout: electron counts (< 2^24) and 10-16-bit codes are exact in it, and its
  // normal sampler is 7x faster than float64's (the simulator feeds training on the fly).
  auto s = signal.to(torch::kFloat32);
  // A full well beyond kCountableElectrons (a camera file's tiny noise_gain) has shot noise far below
  // float32's resolution of the signal, and its electron counts overflow float32 (inf / inf, read back
  // as code 0): such a sensor is read in units of the full well instead, where nothing overflows.
  constexpr double kCountableElectrons = 1e12;
  if (noise && !(rig.full_well <= kCountableElectrons)) {
    const double shot_scale = std::sqrt(1.0 / rig.full_well), read_sigma = rig.read_noise / rig.full_well;
    s = s +
        torch::sqrt(s.clamp_min(0)) * static_cast<float>(shot_scale) *
            at::normal(0.0, 1.0, s.sizes(), gen, s.options()) +
        at::normal(0.0, std::isfinite(read_sigma) ? read_sigma : 0.0, s.sizes(), gen, s.options());
  } else if (noise) {
    auto electrons = photon_electrons(s.clamp_min(0) * static_cast<float>(rig.full_well), gen) +
                     at::normal(0.0, rig.read_noise, s.sizes(), gen, s.options());
    s = electrons / static_cast<float>(rig.full_well);
  }
  s = s + static_cast<float>(rig.dark);
  const double levels = std::pow(2.0, rig.adc_bits) - 1;
  return torch::round(s * static_cast<float>(levels)).clamp(0, levels).to(torch::kInt32);
}

torch::Tensor simulate_raw(const Rig& rig, const torch::Tensor& scene_srgb, bool noise,
                           c10::optional<at::Generator> gen) {
  TORCH_CHECK(scene_srgb.dim() == 3 && scene_srgb.size(0) == 3, "scene must be {3,N,N}");
  return simulate_raw_linear(rig, display_to_light(scene_srgb.to(torch::kFloat32), rig.display_gamma), noise, gen);
}

torch::Tensor simulate_raw_linear(const Rig& rig, const torch::Tensor& scene_linear, bool noise,
                                  c10::optional<at::Generator> gen) {
  TORCH_CHECK(scene_linear.dim() == 3 && scene_linear.size(0) == 3, "scene must be {3,N,N}");
  // A bench's errors (none for a plain rig) where they arise: display, colour, optics, sensor.
  const auto shown = bench_display(rig.bench, scene_linear.to(torch::kFloat32), gen);
  auto planes = rgb_to_bayer_planes(bench_crosstalk(rig.bench, shown)).unsqueeze(0);
  const auto coded = bench_calibration(rig.bench, rig, planes, expected_signal(rig, planes), gen);
  const auto signal = bench_signal(rig.bench, rig, planes, coded);
  auto codes = sensor_readout(rig, signal, noise, gen)[0];  // {4,h,w}
  return bench_hot_pixels(rig.bench, adc_to_stored(bayer_merge(codes), rig.adc_bits), rig.adc_bits);
}

torch::Tensor capture_planes(const Rig& rig, const torch::Tensor& scene_linear, const RawGeometry& g, bool noise,
                             at::Generator& gen) {
  TORCH_CHECK(scene_linear.dim() == 4 && scene_linear.size(1) == 3, "scenes must be {B,3,N,N}");
  require(g.rotation == 0.0, "camera.rotation", "a learned camera's captures are simulated unrotated; it must be 0");
  require(!rig.bench.any(), "camera.bench", "a learned camera's captures are simulated without a bench's errors");
  // Only the window's rows of PhiL and columns of PhiR: the same numbers as the whole plane cropped.
  Rig window_rig = rig;
  window_rig.phil = rig.phil.slice(1, g.crop[0], g.crop[0] + g.crop[2]);
  window_rig.phir = rig.phir.slice(1, g.crop[1], g.crop[1] + g.crop[3]);
  window_rig.vig_rows = rig.vig_rows.slice(0, g.crop[0], g.crop[0] + g.crop[2]);
  window_rig.vig_cols = rig.vig_cols.slice(0, g.crop[1], g.crop[1] + g.crop[3]);
  if (rig.fixed_light.defined())
    window_rig.fixed_light =
        rig.fixed_light.slice(1, g.crop[0], g.crop[0] + g.crop[2]).slice(2, g.crop[1], g.crop[1] + g.crop[3]);
  auto S = expected_signal(window_rig, rgb_to_bayer_planes(scene_linear));  // {B,4,crop_h,crop_w}, full-scale units
  if (noise) {  // electrons ~ N(S fw, S fw) + N(0, read_noise^2): one Gaussian of the summed variance, full-scale units
    const double read_variance = std::pow(rig.read_noise / rig.full_well, 2);
    S = S + torch::sqrt(S.clamp_min(0) / rig.full_well + read_variance + 1e-12) *
                at::normal(0.0, 1.0, S.sizes(), gen, S.options());
  }
  const double levels = std::pow(2.0, rig.adc_bits) - 1;
  const auto analog = (S + rig.dark) * levels;
  const auto codes = (analog + (torch::round(analog) - analog).detach()).clamp(0, levels);  // straight-through rounding
  // Stored 16-bit values (code * 2^(16 - bits)) read back in [0, 1], as load_raw_unit does.
  const auto unit = codes * (std::pow(2.0, 16 - rig.adc_bits) / 65535.0);
  return double_centre(unit, g.centring);
}

namespace {

// A compact shift-structured calibration (save_shift_calibration): each factor one profile per
// channel and its shift, expanded here (optics/shift_structure.hpp eq. 1).
Calibration load_shift_calibration(const MatReader& mat, const std::filesystem::path& path, int64_t h, int64_t w,
                                   int64_t n) {
  const double shift_rows = mat.read_scalar("shift_rows"), shift_cols = mat.read_scalar("shift_cols");
  require(std::isfinite(shift_rows) && std::isfinite(shift_cols) && std::abs(shift_rows) >= 1e-3 &&
              std::abs(shift_cols) >= 1e-3 && std::abs(shift_rows) <= 64 && std::abs(shift_cols) <= 64,
          path, "shift_rows / shift_cols must be finite, 0.001 to 64 sensor pixels per scene pixel");
  // A compact file is one form or the other: full matrices beside it would be ignored without a word.
  for (const char* c : kChannelNames)
    require(!mat.has(std::string("P1") + c) && !mat.has(std::string("Q1") + c), path,
            std::string("holds both a compact calibration (shift_rows, profiles) and full matrices (P1") + c +
                ", ...); keep one form: flatnet cannot tell which one you meant");
  // The profile's length follows from the geometry: checked before anything is expanded.
  const auto length = [&](int64_t m, double shift) { return shift_profile_length(m, n, shift, 1.0); };
  const auto profile = [&](const char* name, int64_t L) {
    auto t = mat.read(name);
    require(t.dim() == 2 && t.size(0) == 4 && t.size(1) >= L && t.size(1) <= L + 1, path,
            std::string(name) + " must be 4 x " + std::to_string(L) + " for this camera's crop, scene and shift");
    require(torch::isfinite(t).all().item<bool>(), path, std::string(name) + " contains NaN or Inf");
    return t.to(torch::kFloat64);
  };
  const auto fr = profile("profile_rows", length(h, shift_rows)), fc = profile("profile_cols", length(w, shift_cols));
  return {shift_factor(fr, h, n, shift_rows, 1.0), shift_factor(fc, w, n, shift_cols, 1.0)};
}

// A factor's entries are a pixel's response to a scene pixel (calibrations seen: largest 0.006 to 2).
// Far outside that, Tikhonov's filter s / (s^2 + lambda) over- or underflows in float32 and every
// picture comes out uniform: refused, named, instead.
constexpr double kSmallestFactorPeak = 1e-6, kLargestFactorPeak = 1e4;

Calibration with_plausible_scale(Calibration calib, const std::filesystem::path& path) {
  for (const auto& [name, factor] : {std::pair{"P (rows)", calib.P}, std::pair{"Q (columns)", calib.Q}}) {
    const double peak = factor.abs().max().item<double>();
    require(peak >= kSmallestFactorPeak && peak <= kLargestFactorPeak, path,
            std::string("the factor ") + name + "'s largest entry is " + std::to_string(peak) +
                ", outside the plausible [1e-06, 1e+04] (a pixel's response to one scene pixel): a calibration "
                "scaled by mistake; rescale it (the pictures' brightness follows the camera's exposure, not this)");
  }
  return calib;
}

// The most bytes a calibration variable for this geometry holds: a factor {m,n}, or a compact file's
// profiles {4, m + |shift| n + 1} with |shift| <= 64. A file claiming more is not this camera's (a
// compressed variable is refused as it inflates past this, before the rest of it is inflated).
uint64_t calibration_bytes_at_most(int64_t h, int64_t w, int64_t n) {
  const auto m = static_cast<uint64_t>(std::max(h, w)), scene = static_cast<uint64_t>(n);
  const auto plane = static_cast<uint64_t>(h) * static_cast<uint64_t>(w);  // a fixed light's plane
  return sizeof(double) * std::max({m * scene, 4 * (m + 64 * scene + 2), plane});
}

std::string fixed_light_name(int channel) { return std::string("fixed_light_") + kChannelNames[channel]; }

// The optional fixed light {4,h,w}: all four planes or none, each the window's size and finite.
torch::Tensor read_fixed_light(const MatReader& mat, const std::filesystem::path& path, int64_t h, int64_t w) {
  int present = 0;
  for (int c = 0; c < 4; ++c) present += mat.has(fixed_light_name(c)) ? 1 : 0;
  if (present == 0) return {};
  require(present == 4, path,
          "holds a fixed light for some Bayer planes but not all four (fixed_light_b, _gb, _gr, _r)");
  std::vector<torch::Tensor> planes;
  for (int c = 0; c < 4; ++c) planes.push_back(mat.read(fixed_light_name(c), {h, w}).to(torch::kFloat64));
  auto F = torch::stack(planes);
  require(torch::isfinite(F).all().item<bool>(), path, "its fixed light holds NaN or Inf");
  return F;
}

Calibration read_factors(const MatReader& mat, const std::filesystem::path& path, int64_t h, int64_t w, int64_t n) {
  std::vector<torch::Tensor> P, Q;
  for (const char* c : kChannelNames) {
    const auto pname = std::string("P1") + c, qname = std::string("Q1") + c;
    auto p = mat.read(pname);
    auto q = mat.read(qname);
    require(p.dim() == 2 && p.size(0) == h && p.size(1) == n, path,
            pname + " is " + std::to_string(p.size(0)) + "x" + std::to_string(p.size(1)) +
                " but the camera's crop gives " + std::to_string(h) + " rows and the scene is " + std::to_string(n) +
                " pixels");
    require(q.dim() == 2 && q.size(0) == w && q.size(1) == n, path,
            qname + " is " + std::to_string(q.size(0)) + "x" + std::to_string(q.size(1)) +
                " but the camera's crop gives " + std::to_string(w) + " columns and the scene is " + std::to_string(n) +
                " pixels");
    require(torch::isfinite(p).all().item<bool>() && torch::isfinite(q).all().item<bool>(), path,
            pname + "/" + qname + " contain NaN or Inf");
    P.push_back(p);
    Q.push_back(q);
  }
  return {torch::stack(P), torch::stack(Q)};
}

Calibration read_calibration(const std::filesystem::path& path, const CameraConfig& camera) {
  const auto h = camera.raw.crop[2], w = camera.raw.crop[3], n = camera.scene_size;
  MatReader mat(path, calibration_bytes_at_most(h, w, n));
  auto calib = mat.has("shift_rows") ? load_shift_calibration(mat, path, h, w, n) : read_factors(mat, path, h, w, n);
  calib.fixed_light = read_fixed_light(mat, path, h, w);
  return calib;
}

}  // namespace

Calibration load_calibration(const std::filesystem::path& path, const CameraConfig& camera) {
  return with_plausible_scale(read_calibration(path, camera), path);
}

namespace {
void add_fixed_light(std::map<std::string, torch::Tensor>& vars, const torch::Tensor& fixed_light) {
  if (!fixed_light.defined()) return;
  for (int c = 0; c < 4; ++c) vars[fixed_light_name(c)] = fixed_light[c].to(torch::kFloat64);
}
}  // namespace

torch::Tensor without_fixed_light(const torch::Tensor& planes, const torch::Tensor& fixed_light) {
  if (!fixed_light.defined()) return planes;
  return planes - fixed_light.to(planes.scalar_type());  // {...,4,h,w} - {4,h,w}
}

void save_shift_calibration(const std::filesystem::path& path, const torch::Tensor& profile_rows,
                            const torch::Tensor& profile_cols, double shift_rows, double shift_cols,
                            const torch::Tensor& fixed_light) {
  std::map<std::string, torch::Tensor> vars = {{"profile_rows", profile_rows.to(torch::kFloat64)},
                                               {"profile_cols", profile_cols.to(torch::kFloat64)},
                                               {"shift_rows", torch::tensor(shift_rows, torch::kFloat64)},
                                               {"shift_cols", torch::tensor(shift_cols, torch::kFloat64)}};
  add_fixed_light(vars, fixed_light);
  write_mat(path, vars);
}

void save_calibration(const std::filesystem::path& path, const Calibration& calib) {
  std::map<std::string, torch::Tensor> vars;
  for (int i = 0; i < 4; ++i) {
    vars[std::string("P1") + kChannelNames[i]] = calib.P[i];
    vars[std::string("Q1") + kChannelNames[i]] = calib.Q[i];
  }
  add_fixed_light(vars, calib.fixed_light);
  write_mat(path, vars);
}

Calibration ideal_calibration(const Rig& rig, const RawGeometry& g) {
  auto centre = [](const torch::Tensor& m) { return m - m.mean(-2, true); };  // C_m M (centred columns)
  auto L = rig.phil.to(torch::kFloat64).index({Slice(), Slice(g.crop[0], g.crop[0] + g.crop[2]), Slice()});
  auto R = rig.phir.to(torch::kFloat64).index({Slice(), Slice(g.crop[1], g.crop[1] + g.crop[3]), Slice()});
  return {rig.gain.to(torch::kFloat64).view({4, 1, 1}) * centre(L), centre(R)};
}

}  // namespace flatnet
