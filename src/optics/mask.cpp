#include "optics/mask.hpp"

#include "core/error.hpp"
#include "io/image.hpp"
#include "optics/codes.hpp"

namespace flatnet {

namespace {

// Rows [r0, r1) and columns [c0, c1) of the element grid that the sensor window sees.
struct Visible {
  int64_t r0, r1, c0, c1;
};

Visible visible_elements(const MaskOptions& o) {
  const int64_t full = o.elements * o.upsample;
  const int64_t top = (full - o.rows) / 2, left = (full - o.cols) / 2;
  return {std::max<int64_t>(0, top / o.upsample), std::min(o.elements, (top + o.rows + o.upsample - 1) / o.upsample),
          std::max<int64_t>(0, left / o.upsample), std::min(o.elements, (left + o.cols + o.upsample - 1) / o.upsample)};
}

}  // namespace

MaskProjection parse_mask_projection(const std::string& s, const std::string& key) {
  if (s == "sigmoid") return MaskProjection::sigmoid;
  if (s == "clamp") return MaskProjection::clamp;
  throw Error(key, "must be sigmoid or clamp, got '" + s + "'");
}

ThroughputRule parse_throughput_rule(const std::string& s, const std::string& key) {
  if (s == "equal") return ThroughputRule::equal;
  if (s == "cap") return ThroughputRule::cap;
  if (s == "free") return ThroughputRule::free;
  throw Error(key, "must be equal, cap or free, got '" + s + "'");
}

MaskInit parse_mask_init(const std::string& s, const std::string& key) {
  if (s == "random") return MaskInit::random;
  if (s == "mls") return MaskInit::mls;
  throw Error(key, "must be random or mls, got '" + s + "'");
}

MaskModelImpl::MaskModelImpl(const MaskOptions& o) : opt_(o) {
  require(o.rank >= 1, "mask.rank", "must be at least 1, got " + std::to_string(o.rank));
  require(o.elements >= 1 && o.upsample >= 1, "mask", "elements and upsample must be positive");
  require(o.target > 0 && o.target < 1, "mask.target_throughput", "must lie in (0, 1)");
  auto gen = at::detail::createCPUGenerator(o.seed);
  // Random init: U V^T entries ~ N(0, 1) (sigmoid logits), or a centred transmittance for clamp.
  auto u = at::randn({o.elements, o.rank}, gen) / std::pow(static_cast<double>(o.rank), 0.25);
  auto v = at::randn({o.elements, o.rank}, gen) / std::pow(static_cast<double>(o.rank), 0.25);
  if (o.init == MaskInit::mls) {
    // The MLS mask: (m m^T + 1) / 2 is 0/1; as logits, +-4 (sigmoid) or the values (clamp, + shift).
    const auto code = mls(9);
    require(static_cast<int64_t>(code.size()) == o.elements, "mask.init", "mls needs 511 elements");
    auto m = torch::tensor(std::vector<float>(code.begin(), code.end()));
    const float scale = o.projection == MaskProjection::sigmoid ? 2.0f : 0.7071f;
    u = u * 0.05;
    v = v * 0.05;
    u.select(1, 0).copy_(m * scale);
    v.select(1, 0).copy_(m * scale);
  } else {
    if (o.projection == MaskProjection::clamp) u = u * 0.5, v = v * 0.5;
  }
  U = register_parameter("U", u);
  V = register_parameter("V", v);
}

torch::Tensor MaskModelImpl::transmittance() {
  const auto A = torch::matmul(U, V.t());  // {E,E}
  const bool sigmoid = opt_.projection == MaskProjection::sigmoid;
  auto f = [&](const torch::Tensor& z) { return sigmoid ? torch::sigmoid(z) : z.clamp(0, 1); };
  const auto vis = visible_elements(opt_);
  auto visible = [&](const torch::Tensor& m) { return m.slice(0, vis.r0, vis.r1).slice(1, vis.c0, vis.c1); };
  // Throughput rule: shift the logits by b so that the window's mean transmittance is the target.
  double b = 0;
  bool shifted = false;
  if (opt_.throughput != ThroughputRule::free) {
    torch::NoGradGuard no_grad;
    // Only the elements the sensor sees enter the mean, so bisect on those alone.
    const auto Av = visible(A.detach()).contiguous();
    if (opt_.throughput == ThroughputRule::equal || f(Av).mean().item<double>() > opt_.target) {
      double lo = -60, hi = 60;
      for (int it = 0; it < 60; ++it) {
        const double mid = 0.5 * (lo + hi);
        (f(Av + mid).mean().item<double>() > opt_.target ? hi : lo) = mid;
      }
      b = 0.5 * (lo + hi);
      shifted = true;
    }
  }
  const auto Z = A + b;
  auto M = f(Z);
  if (shifted) {
    // b depends on A (mean fixed): its exact gradient removes, over the visible elements, the
    // component of dL/dM that would change the mean:  dM_i/dZ_j = w_i (delta_ij - w_j / sum w).
    auto w = (sigmoid ? M * (1 - M) : ((Z > 0) & (Z < 1)).to(M.dtype())).detach();
    auto in_window = torch::zeros_like(w);
    in_window.slice(0, vis.r0, vis.r1).slice(1, vis.c0, vis.c1).fill_(1);
    w = w * in_window;
    const auto s = w.sum();
    if (s.item<double>() > 0) {
      const auto wz = (w * Z).sum();
      M = M - w * (wz - wz.detach()) / s;
    }
  }
  if (opt_.binary) {
    // Straight-through: forward a 0/1 mask (open where M is above the quantile that keeps the
    // window's throughput), backward the gradient of M.
    torch::Tensor thr;
    {
      torch::NoGradGuard no_grad;
      const auto seen = visible(M.detach()).flatten();
      const double q =
          opt_.throughput == ThroughputRule::free ? 0.5 : 1.0 - std::min(opt_.target, seen.mean().item<double>());
      thr = torch::quantile(seen, q);
    }
    const auto hard = (M.detach() > thr).to(M.dtype());
    M = M + (hard - M).detach();
  }
  return M;
}

torch::Tensor MaskModelImpl::window() { return mask_window(transmittance(), opt_.upsample, opt_.rows, opt_.cols); }

torch::Tensor mask_window(const torch::Tensor& mask, int64_t up, int64_t rows, int64_t cols) {
  auto m = mask.repeat_interleave(up, 0).repeat_interleave(up, 1);  // {E*up, E*up}
  // Pad (opaque) when the mask is smaller than the sensor, then take the centred window.
  const int64_t pr = std::max<int64_t>(0, rows - m.size(0)), pc = std::max<int64_t>(0, cols - m.size(1));
  if (pr > 0 || pc > 0) m = torch::constant_pad_nd(m, {pc / 2, pc - pc / 2, pr / 2, pr - pr / 2}, 0);
  const int64_t top = (m.size(0) - rows) / 2, left = (m.size(1) - cols) / 2;
  return m.slice(0, top, top + rows).slice(1, left, left + cols);
}

torch::Tensor mls_mask() {
  const auto code = mls(9);  // 511 elements, +-1
  const auto m = torch::tensor(std::vector<float>(code.begin(), code.end()));
  return (torch::outer(m, m) > 0).to(torch::kFloat32);  // -1 -> 0
}

torch::Tensor m02_mask() {
  const auto code = flatnet_m02_pattern();
  const auto m = torch::tensor(std::vector<float>(code.begin(), code.end()));
  return torch::outer(m, m);
}

double throughput(const torch::Tensor& window) { return window.mean().item<double>(); }

torch::Tensor psf_spectrum(const torch::Tensor& window) {
  const int64_t rows = window.size(0), cols = window.size(1);
  const auto p = window / (0.5 * rows * cols);
  return torch::fft::rfft2(torch::roll(p, {-rows / 2, -cols / 2}, {0, 1}));
}

namespace {
int64_t scene_top(const WienerCamera& c) { return (c.rows - c.scene) / 2; }
int64_t scene_left(const WienerCamera& c) { return (c.cols - c.scene) / 2; }
}  // namespace

torch::Tensor capture(const torch::Tensor& scenes, const torch::Tensor& P, const WienerCamera& cam,
                      c10::optional<at::Generator> gen) {
  auto canvas = torch::zeros({scenes.size(0), cam.rows, cam.cols}, scenes.options());
  canvas.slice(1, scene_top(cam), scene_top(cam) + cam.scene)
      .slice(2, scene_left(cam), scene_left(cam) + cam.scene)
      .copy_(scenes);
  auto y = torch::fft::irfft2(torch::fft::rfft2(canvas) * P, c10::IntArrayRef({cam.rows, cam.cols}));
  if (cam.photons > 0) {
    torch::NoGradGuard no_grad;
    const auto counts = at::poisson(y.detach().clamp_min(0) * cam.photons, gen) / cam.photons;
    y = y + (counts - y.detach());
  }
  if (cam.noise_sigma > 0) y = y + cam.noise_sigma * at::randn(y.sizes(), gen);
  return y;
}

torch::Tensor wiener(const torch::Tensor& y, const torch::Tensor& P, const torch::Tensor& gamma,
                     const WienerCamera& cam) {
  const auto filter = P.conj() / (P.abs().pow(2) + gamma);
  const auto x = torch::fft::irfft2(torch::fft::rfft2(y) * filter, c10::IntArrayRef({cam.rows, cam.cols}));
  return x.slice(1, scene_top(cam), scene_top(cam) + cam.scene).slice(2, scene_left(cam), scene_left(cam) + cam.scene);
}

torch::Tensor load_mask_window(const std::string& what, const WienerCamera& cam, int64_t upsample) {
  if (what == "mls") return mask_window(mls_mask(), upsample, cam.rows, cam.cols);
  if (what == "m02") return mask_window(m02_mask(), upsample, cam.rows, cam.cols);
  const std::filesystem::path path(what);
  require(std::filesystem::exists(path), path, "no such mask (give a mask PNG, mls or m02)");
  const auto codes = read_gray16(path);  // errors name the file for non-16-bit or colour images
  require(codes.size(0) == cam.rows && codes.size(1) == cam.cols, path,
          "mask is " + std::to_string(codes.size(0)) + "x" + std::to_string(codes.size(1)) + ", expected " +
              std::to_string(cam.rows) + "x" + std::to_string(cam.cols) + " (the sensor window)");
  return codes.to(torch::kFloat32) / 65535.0f;
}

}  // namespace flatnet
