#include "optics/separable_camera.hpp"

#include <cmath>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/mat.hpp"

namespace flatnet {

torch::Tensor code_matrix(const torch::Tensor& code, int64_t rows, int64_t scene, double offset,
                          double pixels_per_feature, int subsamples) {
  TORCH_CHECK(code.dim() == 1 && code.numel() > 0, "code_matrix: a 1-D code expected");
  const auto f64 = torch::TensorOptions().dtype(torch::kFloat64);
  const auto i = torch::arange(rows, f64).view({rows, 1, 1});
  const auto j = torch::arange(scene, f64).view({1, scene, 1});
  const auto k = torch::arange(subsamples, f64).view({1, 1, subsamples});
  // Evaluated in the README's order, in float64, so the indices are exactly rig.mat's.
  const auto t = (subsamples * i + k + 0.5) / subsamples / pixels_per_feature;
  const auto s = t + (static_cast<double>(scene - 1) - j) + offset;
  const auto index = torch::remainder(torch::floor(s), static_cast<double>(code.numel())).to(torch::kLong);
  return code.index_select(0, index.flatten()).view({rows, scene, subsamples}).mean(2);
}

torch::Tensor blur_rows(const torch::Tensor& m, double sigma) {
  if (sigma <= 0) return m;
  const int64_t radius = static_cast<int64_t>(4.0 * sigma + 0.5), rows = m.size(0);
  std::vector<double> w(2 * radius + 1);
  double total = 0;
  for (int64_t x = -radius; x <= radius; ++x) total += w[x + radius] = std::exp(-0.5 * x * x / (sigma * sigma));
  const auto padded = torch::cat(
      {m.slice(0, 0, 1).expand({radius, m.size(1)}), m, m.slice(0, rows - 1, rows).expand({radius, m.size(1)})});
  torch::Tensor out = torch::zeros_like(m);
  for (int64_t x = 0; x <= 2 * radius; ++x) out = out + (w[x] / total) * padded.slice(0, x, x + rows);
  return out;
}

namespace {

torch::Tensor vignette(int64_t n, double f, const torch::TensorOptions& options) {
  const auto x = (torch::arange(n, options) + 0.5) / static_cast<double>(n) - 0.5;
  return 1.0 / (1.0 + f * x * x).pow(2);
}

}  // namespace

Rig separable_rig(const torch::Tensor& u, const torch::Tensor& v, const SeparableCameraOptions& o) {
  TORCH_CHECK(u.dim() == 1 && v.dim() == 1, "separable_rig: codes u and v must be vectors");
  const auto opts = u.options();
  std::vector<torch::Tensor> L, R, G;
  const auto code_l = code_matrix(u, o.plane_rows, o.scene, o.offset_rows, o.pixels_per_feature, o.subsamples);
  const auto code_r = code_matrix(v, o.plane_cols, o.scene, o.offset_cols, o.pixels_per_feature, o.subsamples);
  const auto vig_l = vignette(o.plane_rows, o.vignette_rows, opts).unsqueeze(1);
  const auto vig_r = vignette(o.plane_cols, o.vignette_cols, opts).unsqueeze(1);
  const double unit_gain = 0.5 * 0.45 / (0.5 * static_cast<double>(o.scene * o.scene) * 0.2);
  for (int c = 0; c < 4; ++c) {
    L.push_back(blur_rows(code_l, o.blur_sigma[c]) * vig_l);
    R.push_back(blur_rows(code_r, o.blur_sigma[c]) * vig_r);
    G.push_back(torch::tensor(unit_gain * o.channel_gain[c], opts));
  }
  Rig rig;
  rig.phil = torch::stack(L);
  rig.phir = torch::stack(R);
  rig.gain = torch::stack(G);
  // The open half of the mask carries its mean transmittance t = (1 + mean(u) mean(v)) / 2.
  const auto open = torch::sqrt(2.0 * (1.0 + u.mean() * v.mean()) / 2.0);
  rig.vig_rows = vignette(o.plane_rows, o.vignette_rows, opts) * open;
  rig.vig_cols = vignette(o.plane_cols, o.vignette_cols, opts) * open;
  rig.full_well = o.full_well;
  rig.read_noise = o.read_noise;
  rig.dark = o.dark;
  rig.adc_bits = o.adc_bits;
  return rig;
}

Calibration calibration_of(const Rig& rig, const std::array<int64_t, 4>& crop, double relative_error, uint64_t seed) {
  const int64_t top = crop[0], left = crop[1], h = crop[2], w = crop[3];
  TORCH_CHECK(top + h <= rig.phil.size(1) && left + w <= rig.phir.size(1),
              "calibration_of: the crop leaves the sensor plane");
  auto gen = at::detail::createCPUGenerator(seed);
  auto measure = [&](const torch::Tensor& phi, int64_t start, int64_t n, const torch::Tensor& gain) {
    auto window = phi.detach().to(torch::kFloat64).slice(0, start, start + n) * std::sqrt(gain.item<double>());
    window = window - window.mean(0, true);  // C_n = I - 1/n: the double centring's column part
    const auto error = at::normal(0.0, 1.0, window.sizes(), gen, torch::TensorOptions().dtype(torch::kFloat64));
    return window + error * (relative_error * window.norm().item<double>() / error.norm().item<double>());
  };
  std::vector<torch::Tensor> P, Q;
  for (int c = 0; c < 4; ++c) {
    P.push_back(measure(rig.phil[c], top, h, rig.gain[c]));
    Q.push_back(measure(rig.phir[c], left, w, rig.gain[c]));
  }
  return {torch::stack(P), torch::stack(Q)};
}

torch::Tensor code_throughput(const torch::Tensor& u, const torch::Tensor& v) { return (1 + u.mean() * v.mean()) / 2; }

torch::Tensor throughput_penalty(const torch::Tensor& throughput, double target, double tolerance) {
  return 100.0 * torch::relu(torch::abs(throughput - target) - tolerance).pow(2);
}

torch::Tensor straight_through_sign(const torch::Tensor& x) { return x + (torch::sign(x) - x).detach(); }

void save_code_pair(const std::filesystem::path& path, const torch::Tensor& rows, const torch::Tensor& cols) {
  write_mat(path, {{"code_rows", rows.detach().to(torch::kFloat64).view({-1, 1})},
                   {"code_cols", cols.detach().to(torch::kFloat64).view({-1, 1})}});
}

void write_code_pair_camera(const std::filesystem::path& folder, const CodePair& codes, CameraConfig camera,
                            double calib_error, uint64_t seed, const std::string& comment,
                            const SeparableCameraOptions& options) {
  std::filesystem::create_directories(folder);
  const auto rig = separable_rig(codes.rows.to(torch::kFloat64), codes.cols.to(torch::kFloat64), options);
  camera.name = folder.filename().string();
  save_rig(folder / "rig.mat", rig);
  save_calibration(folder / "calib.mat", calibration_of(rig, camera.raw.crop, calib_error, seed));
  write_text_atomically(folder / "camera.yaml", "# " + comment + "\n" + camera_geometry_yaml(camera) +
                                                    "calibration: calib.mat\nrig: rig.mat\n");
}

double CodePair::throughput() const { return (1 + rows.mean().item<double>() * cols.mean().item<double>()) / 2; }

CodePair load_code_pair(const std::filesystem::path& path) {
  MatReader codes(path);
  auto vector_of = [&](const char* name) {
    const auto t = codes.read(name);
    require(t.dim() <= 2 && t.numel() >= 2 && (t.dim() < 2 || t.size(0) == 1 || t.size(1) == 1), path,
            std::string("variable '") + name + "' must be a vector");
    const auto v = t.flatten().to(torch::kFloat64);
    require(torch::isfinite(v).all().item<bool>() && v.abs().max().item<double>() <= 1.0 + 1e-9, path,
            std::string("variable '") + name + "' must hold values in [-1, 1]");
    return v;
  };
  return {vector_of("code_rows"), vector_of("code_cols")};
}

void save_rig(const std::filesystem::path& path, const Rig& rig) {
  auto scalar = [](double v) { return torch::full({1, 1}, v, torch::kFloat64); };
  std::map<std::string, torch::Tensor> vars;
  for (int c = 0; c < 4; ++c) {
    const std::string name = kChannelNames[c];
    vars["PhiL_" + name] = rig.phil[c].detach().to(torch::kFloat64);
    vars["PhiR_" + name] = rig.phir[c].detach().to(torch::kFloat64);
    vars["gain_" + name] = scalar(rig.gain[c].item<double>());
  }
  vars["vig_rows"] = rig.vig_rows.detach().to(torch::kFloat64).view({-1, 1});
  vars["vig_cols"] = rig.vig_cols.detach().to(torch::kFloat64).view({-1, 1});
  vars["full_well"] = scalar(rig.full_well);
  vars["read_noise"] = scalar(rig.read_noise);
  vars["dark"] = scalar(rig.dark);
  vars["adc_bits"] = scalar(rig.adc_bits);
  write_mat(path, vars);
}

}  // namespace flatnet
