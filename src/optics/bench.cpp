#include "optics/bench.hpp"

#include <ATen/CPUGeneratorImpl.h>

#include <cmath>

#include "optics/camera.hpp"

namespace flatnet {

namespace {

namespace F = torch::nn::functional;

// Resamples images {B,C,H,W} at theta's affine map of the output's normalised coordinates
// (bilinear, zeros outside, align_corners false: pixel centres).
torch::Tensor warp(const torch::Tensor& images, const torch::Tensor& theta) {
  const auto grid = F::affine_grid(theta.to(images.dtype()), images.sizes(), /*align_corners=*/false);
  return F::grid_sample(
      images, grid, F::GridSampleFuncOptions().mode(torch::kBilinear).padding_mode(torch::kZeros).align_corners(false));
}

}  // namespace

torch::Tensor bench_display(const BenchErrors& bench, const torch::Tensor& scene_linear,
                            c10::optional<at::Generator> gen) {
  auto scene = scene_linear;  // {3,N,N}
  if (bench.display_shift != 0 || bench.display_scale != 1) {
    // Output pixel p shows the photograph at (p - centre - shift) / scale + centre; in normalised
    // coordinates (the square's half side is 1) the shift is 2 shift / N.
    const double n = static_cast<double>(scene.size(-1)), a = 1.0 / bench.display_scale;
    const double t = -2.0 * bench.display_shift / n * a;
    const auto theta = torch::tensor({a, 0.0, t, 0.0, a, t}, torch::kFloat64).view({1, 2, 3});
    scene = warp(scene.unsqueeze(0), theta)[0];
  }
  if (bench.flicker > 0) {
    const auto z = at::normal(0.0, 1.0, {1}, gen, scene.options()).item<double>();
    scene = scene * std::exp(bench.flicker * z);
  }
  return scene;
}

torch::Tensor bench_crosstalk(const BenchErrors& bench, const torch::Tensor& rgb) {
  if (bench.crosstalk == 0) return rgb;
  const double c = bench.crosstalk;
  const auto mix = torch::full({3, 3}, c / 2, rgb.options()) + torch::eye(3, rgb.options()) * (1 - c - c / 2);
  return torch::einsum("ij,jhw->ihw", {mix, rgb});  // {3,N,N}
}

torch::Tensor bench_signal(const BenchErrors& bench, const Rig& rig, const torch::Tensor& planes,
                           const torch::Tensor& signal) {
  auto s = signal;  // {1,4,h,w}
  if (bench.second_term > 0) {
    const auto phil = torch::roll(rig.phil, 9, 1), phir = torch::roll(rig.phir, -7, 1);
    const auto ghost = torch::matmul(torch::matmul(phil, planes.to(torch::kFloat32)), phir.transpose(1, 2));
    s = s + bench.second_term * rig.gain.view({1, 4, 1, 1}) * ghost;
  }
  if (bench.mask_rotation != 0) {
    // Pixel coordinates rotate by the angle about the centre; normalised ones carry the aspect
    // ratio: x_in = c x - s (h / w) y, y_in = s (w / h) x + c y.
    const double c = std::cos(bench.mask_rotation), si = std::sin(bench.mask_rotation);
    const double h = static_cast<double>(s.size(2)), w = static_cast<double>(s.size(3));
    const auto theta = torch::tensor({c, -si * h / w, 0.0, si * w / h, c, 0.0}, torch::kFloat64).view({1, 2, 3});
    s = warp(s, theta);
  }
  if (bench.stray_light > 0) {
    const auto rows = torch::linspace(0, 0.5, s.size(2), s.options()).view({-1, 1});
    const auto cols = torch::linspace(0, 0.5, s.size(3), s.options()).view({1, -1});
    s = s + bench.stray_light * (rows + cols);
  }
  return s;
}

torch::Tensor bench_calibration(const BenchErrors& bench, const Rig& rig, const torch::Tensor& planes,
                                const torch::Tensor& signal, c10::optional<at::Generator> gen) {
  if (bench.calibration_error <= 0) return signal;
  const auto X = planes.to(torch::kFloat32);
  const auto coded = [&](const torch::Tensor& L, const torch::Tensor& R) {  // {1,4,h,w}
    return torch::matmul(torch::matmul(L, X), R.transpose(1, 2));
  };
  // Each factor plus iid Gaussian entries; the change that makes in the coded light is then scaled,
  // per channel, to calibration_error of that light (what leave-one-out measures on real scenes).
  const auto erred = [&](const torch::Tensor& phi) {
    return phi + at::normal(0.0, 1.0, phi.sizes(), gen, phi.options()) * phi.abs().mean();
  };
  const auto light = coded(rig.phil, rig.phir);
  const auto change = coded(erred(rig.phil), erred(rig.phir)) - light;
  const auto scale = light.norm(2, {2, 3}, true) / change.norm(2, {2, 3}, true).clamp_min(1e-30);
  return signal + rig.gain.view({1, 4, 1, 1}) * change * (bench.calibration_error * scale);
}

torch::Tensor bench_hot_pixels(const BenchErrors& bench, const torch::Tensor& raw, int adc_bits) {
  if (bench.hot_pixels <= 0) return raw;
  auto gen = at::make_generator<at::CPUGeneratorImpl>(7919 + static_cast<uint64_t>(raw.numel()));
  const auto count = std::min<int64_t>(bench.hot_pixels, raw.numel());
  const auto places = torch::randperm(raw.numel(), gen, torch::kInt64).slice(0, 0, count);
  const double levels = std::pow(2.0, adc_bits) - 1, step = std::pow(2.0, 16 - adc_bits);
  const auto level = torch::round((0.4 + 0.6 * at::rand({count}, gen, torch::kFloat64)) * levels) * step;
  auto out = raw.clone().view(-1);
  out.index_put_({places}, torch::maximum(out.index({places}), level.to(out.dtype())));
  return out.view(raw.sizes());
}

}  // namespace flatnet
