#include "optics/calibrate.hpp"

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"
#include "optics/codes.hpp"

namespace flatnet {

namespace {
std::string pattern_name(const char* axis, int64_t k, const char* sign) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "%s_%03lld_%s", axis, static_cast<long long>(k), sign);
  return buf;
}
}  // namespace

double pattern_level_linear(int level_code) {
  require(level_code > 0 && level_code <= 255, "pattern level", "must be a display code within 1..255");
  const double v = level_code / 255.0;
  return v <= 0.04045 ? v / 12.92 : std::pow((v + 0.055) / 1.055, 2.4);
}

std::vector<CalibrationPattern> calibration_patterns(int64_t N, int level_code) {
  const float level = static_cast<float>(level_code / 255.0);
  pattern_level_linear(level_code);  // validates
  const auto H = hadamard(N).to(torch::kFloat32);
  std::vector<CalibrationPattern> out;
  auto ones = torch::ones({N}, torch::kFloat32);
  for (const char* axis : {"row", "col"}) {
    for (int64_t k = 0; k < N; ++k) {
      auto pos = (1 + H.select(1, k)) / 2, neg = (1 - H.select(1, k)) / 2;
      const bool row = axis[0] == 'r';
      out.push_back({pattern_name(axis, k, "pos"), level * (row ? torch::outer(pos, ones) : torch::outer(ones, pos))});
      out.push_back({pattern_name(axis, k, "neg"), level * (row ? torch::outer(neg, ones) : torch::outer(ones, neg))});
    }
  }
  return out;
}

Calibration estimate_calibration(int64_t N, const std::function<torch::Tensor(const std::string&)>& capture,
                                 int level_code, bool show_progress) {
  const double level = pattern_level_linear(level_code);
  const auto H = hadamard(N);             // {N,N} float64
  std::vector<torch::Tensor> drow, dcol;  // N each, {4,h,w} float64
  Progress progress("calibrate", 4 * N, show_progress);
  for (const char* axis : {"row", "col"}) {
    auto& d = axis[0] == 'r' ? drow : dcol;
    for (int64_t k = 0; k < N; ++k) {
      auto pos = capture(pattern_name(axis, k, "pos")).to(torch::kFloat64);
      auto neg = capture(pattern_name(axis, k, "neg")).to(torch::kFloat64);
      d.push_back((pos - neg) / level);  // response to a unit-contrast pattern
      progress.tick(2);
    }
  }
  progress.finish();
  // Common factors: b = Q 1 spans the rows of every D_k^row (k > 0), a = P 1 the columns of D_k^col.
  auto gram_r = torch::zeros({4, drow[0].size(2), drow[0].size(2)}, torch::kFloat64);
  auto gram_c = torch::zeros({4, dcol[0].size(1), dcol[0].size(1)}, torch::kFloat64);
  for (int64_t k = 1; k < N; ++k) {
    gram_r += torch::matmul(drow[k].transpose(1, 2), drow[k]);
    gram_c += torch::matmul(dcol[k], dcol[k].transpose(1, 2));
  }
  auto b_hat = std::get<1>(torch::linalg_eigh(gram_r)).select(2, -1);  // {4,w} top eigenvector
  auto a_hat = std::get<1>(torch::linalg_eigh(gram_c)).select(2, -1);  // {4,h}
  // Scale (and relative sign) from the all-white minus all-black capture: D_0 ~= a b^T.
  auto d0 = 0.5 * (drow[0] + dcol[0]);
  auto sigma = torch::matmul(a_hat.unsqueeze(1), torch::matmul(d0, b_hat.unsqueeze(2))).view({4});  // a^ D0 b^
  require((sigma.abs() > 0).all().item<bool>(), "calibration captures", "all-white capture carries no signal");
  auto a = a_hat * torch::sqrt(sigma.abs()).unsqueeze(1);
  auto b = b_hat * (torch::sqrt(sigma.abs()) * torch::sign(sigma)).unsqueeze(1);
  // Columns P h_k and Q h_k (k = 0 is a and b themselves).
  std::vector<torch::Tensor> Ph{a}, Qh{b};
  auto bb = (b * b).sum(1).view({4, 1}), aa = (a * a).sum(1).view({4, 1});
  for (int64_t k = 1; k < N; ++k) {
    Ph.push_back(torch::matmul(drow[k], b.unsqueeze(2)).squeeze(2) / bb);
    Qh.push_back(torch::matmul(dcol[k].transpose(1, 2), a.unsqueeze(2)).squeeze(2) / aa);
  }
  auto PH = torch::stack(Ph, 2), QH = torch::stack(Qh, 2);  // {4,h,N}, {4,w,N}
  return {torch::matmul(PH, H.t()) / static_cast<double>(N), torch::matmul(QH, H.t()) / static_cast<double>(N)};
}

std::function<torch::Tensor(const std::string&)> rig_pattern_capture(const Rig& rig, const RawGeometry& g,
                                                                     int level_code, bool noise, int average,
                                                                     at::Generator gen) {
  auto patterns = std::make_shared<std::map<std::string, torch::Tensor>>();
  for (auto& p : calibration_patterns(rig.scene_size(), level_code)) (*patterns)[p.name] = p.image;
  return [&rig, g, patterns, noise, average, gen](const std::string& name) {
    auto X = srgb_to_linear(patterns->at(name)).unsqueeze(0).unsqueeze(0).expand({1, 4, -1, -1});
    auto S = expected_signal(rig, X);
    torch::Tensor sum;
    for (int k = 0; k < std::max(1, average); ++k) {
      auto codes = sensor_readout(rig, S, noise, gen)[0];
      auto raw = adc_to_stored(bayer_merge(codes), rig.adc_bits).to(torch::kFloat32) / 65535.0f;
      sum = k == 0 ? raw : sum + raw;
    }
    return without_level(preprocess_raw(sum / std::max(1, average), g), g.centring);
  };
}

CalibrationError calibration_error(const Calibration& est, const Calibration& truth, const torch::Tensor& scene) {
  auto aligned = [](const torch::Tensor& e, const torch::Tensor& t) {
    auto alpha = (e * t).sum({1, 2}) / (e * e).sum({1, 2});  // best scalar per channel
    auto err = (alpha.view({-1, 1, 1}) * e - t).norm(2, {1, 2}) / t.norm(2, {1, 2});
    return err.mean().item<double>();
  };
  CalibrationError out;
  out.p = aligned(est.P.to(torch::kFloat64), truth.P.to(torch::kFloat64));
  out.q = aligned(est.Q.to(torch::kFloat64), truth.Q.to(torch::kFloat64));
  auto gen = at::detail::createCPUGenerator(7);
  const auto N = truth.P.size(2);
  const auto X = scene.defined() ? scene.to(torch::kFloat64)
                                 : at::rand({4, N, N}, gen, torch::TensorOptions().dtype(torch::kFloat64));
  auto fwd = [&](const Calibration& c) {
    return torch::matmul(torch::matmul(c.P.to(torch::kFloat64), X), c.Q.to(torch::kFloat64).transpose(1, 2));
  };
  auto yt = fwd(truth);
  out.forward = ((fwd(est) - yt).norm() / yt.norm()).item<double>();
  return out;
}

}  // namespace flatnet
