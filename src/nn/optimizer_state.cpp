#include "nn/optimizer_state.hpp"

#include <cmath>

#include <ATen/CPUGeneratorImpl.h>

#include "core/error.hpp"

namespace flatnet {

void require_adam_moments(int64_t step, const torch::Tensor& exp_avg, const torch::Tensor& exp_avg_sq,
                          const std::filesystem::path& path, const std::string& what) {
  require(step >= 0, path, "'" + what + "step' is " + std::to_string(step) + "; a step count is >= 0");
  require(torch::isfinite(exp_avg).all().item<bool>(), path, "'" + what + "exp_avg' holds NaN or infinity");
  require(torch::isfinite(exp_avg_sq).all().item<bool>(), path, "'" + what + "exp_avg_sq' holds NaN or infinity");
  require(exp_avg_sq.numel() == 0 || exp_avg_sq.min().item<double>() >= 0, path,
          "'" + what + "exp_avg_sq' holds negative values; Adam's second moment is a mean of squares (>= 0)");
}

void require_adam_options(double beta1, double beta2, double eps, double lr, double weight_decay,
                          const std::filesystem::path& path, const std::string& what) {
  const auto in_unit = [](double b) { return std::isfinite(b) && b >= 0 && b < 1; };
  require(in_unit(beta1) && in_unit(beta2), path,
          what + " betas [" + std::to_string(beta1) + ", " + std::to_string(beta2) + "] are not both in [0, 1)");
  require(std::isfinite(eps) && eps > 0, path, what + " eps " + std::to_string(eps) + " is not a positive number");
  require(std::isfinite(lr) && lr >= 0, path, what + " learning rate " + std::to_string(lr) + " is not >= 0");
  require(std::isfinite(weight_decay) && weight_decay >= 0, path,
          what + " weight decay " + std::to_string(weight_decay) + " is not >= 0");
}

void require_cpu_generator_state(const torch::Tensor& state, const std::filesystem::path& path,
                                 const std::string& what) {
  const auto expected = at::detail::getDefaultCPUGenerator().get_state();
  require(state.defined() && state.scalar_type() == torch::kUInt8 && state.sizes() == expected.sizes(), path,
          "'" + what + "' is not a state of LibTorch's random generator (" + std::to_string(expected.numel()) +
              " bytes expected)");
  auto scratch = at::detail::createCPUGenerator();
  try {
    scratch.set_state(state.contiguous());
  } catch (const c10::Error&) {
    throw Error(path, "'" + what + "' is not a valid state of LibTorch's random generator (damaged or edited)");
  }
}

}  // namespace flatnet
