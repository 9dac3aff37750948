#include "eval/mask_score.hpp"

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"

namespace flatnet {

torch::Tensor load_luma_scenes(const std::vector<std::filesystem::path>& images, int64_t size, int workers) {
  require(!images.empty(), "images", "no readable images");
  auto out = torch::empty({static_cast<int64_t>(images.size()), size, size});
  parallel_for_index(out.size(0), workers, [&](int64_t i) {
    const auto rgb = resize(read_rgb(images[i]), size, size).clamp(0, 1);
    out[i].copy_(0.299f * rgb[0] + 0.587f * rgb[1] + 0.114f * rgb[2]);
  });
  return out;
}

double psnr_sum(const torch::Tensor& rec, const torch::Tensor& truth) {  // {B,N,N}
  const auto mse = (rec.clamp(0, 1) - truth).pow(2).mean({1, 2}).clamp_min(1e-12);
  return (-10.0 * torch::log10(mse)).sum().item<double>();
}

double mask_psnr(const torch::Tensor& window, double gamma, const torch::Tensor& scenes, const WienerCamera& cam,
                 uint64_t seed, int64_t batch) {
  torch::NoGradGuard no_grad;
  const auto P = psf_spectrum(window);
  const auto g = torch::tensor(gamma);
  double sum = 0;
  for (int64_t i = 0; i < scenes.size(0); i += batch) {
    const auto x = scenes.slice(0, i, std::min(scenes.size(0), i + batch));
    auto gen = at::detail::createCPUGenerator(seed * 1000003ULL + static_cast<uint64_t>(i));
    sum += psnr_sum(wiener(capture(x, P, cam, gen), P, g, cam), x);
  }
  return sum / scenes.size(0);
}

double tune_gamma(const torch::Tensor& window, const torch::Tensor& scenes, const WienerCamera& cam, uint64_t seed) {
  double best = -1e9, best_log = -3;
  for (double lg = -8; lg <= 0.01; lg += 0.5) {
    const double p = mask_psnr(window, std::pow(10.0, lg), scenes, cam, seed);
    if (p > best) best = p, best_log = lg;
  }
  const double centre = best_log;
  for (double lg = centre - 0.4; lg <= centre + 0.41; lg += 0.1) {
    const double p = mask_psnr(window, std::pow(10.0, lg), scenes, cam, seed);
    if (p > best) best = p, best_log = lg;
  }
  return std::pow(10.0, best_log);
}

}  // namespace flatnet
