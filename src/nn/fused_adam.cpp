#include "nn/fused_adam.hpp"

#include <ATen/Parallel.h>
#include <ATen/record_function.h>

#include <cmath>

namespace flatnet {

namespace {

// Whether p, its gradient and both moments are fp32 and lie over the same dense memory layout, so
// that element i of each is the i-th float from its data pointer.
bool one_pass_layout(const torch::Tensor& p, const torch::Tensor& grad, const torch::Tensor& m,
                     const torch::Tensor& v) {
  for (const auto* t : {&p, &grad, &m, &v})
    if (t->scalar_type() != torch::kFloat32 || t->is_sparse() || !t->is_non_overlapping_and_dense() ||
        t->strides() != p.strides() || t->sizes() != p.sizes())
      return false;
  return true;
}

struct AdamScalars {
  float beta1, beta2, weight_decay, root_bias_correction2, eps, step_size;
};

// One Adam update (torch::optim::Adam, amsgrad off) of elements [begin, end), in ATen's order:
//   m = beta1 m + (1 - beta1) g;  v = beta2 v + (1 - beta2) g^2;
//   p -= step_size m / (sqrt(v) / sqrt(bias_correction2) + eps)
// Built for AVX-512, AVX2 with FMA and the baseline, chosen when the program loads (GCC's
// target_clones). CMakeLists.txt builds this file without math errno, so that sqrt vectorises.
__attribute__((target_clones("arch=skylake-avx512", "arch=haswell", "default"))) void update_range(
    float* __restrict p, const float* __restrict g, float* __restrict m, float* __restrict v, int64_t begin,
    int64_t end, AdamScalars s) {
  for (int64_t i = begin; i < end; ++i) {
    const float grad = g[i] + s.weight_decay * p[i];        // grad.add(p, weight_decay)
    m[i] = m[i] * s.beta1 + (1.f - s.beta1) * grad;         // exp_avg.mul_(beta1).add_(grad, 1 - beta1)
    v[i] = v[i] * s.beta2 + (1.f - s.beta2) * grad * grad;  // exp_avg_sq.mul_(beta2).addcmul_(grad, grad, 1 - beta2)
    const float denom = std::sqrt(v[i]) / s.root_bias_correction2 + s.eps;
    p[i] = p[i] + (-s.step_size) * m[i] / denom;  // p.addcdiv_(exp_avg, denom, -step_size)
  }
}

void update(float* p, const float* g, float* m, float* v, int64_t n, const AdamScalars& s) {
  at::parallel_for(0, n, 32768, [&](int64_t begin, int64_t end) { update_range(p, g, m, v, begin, end, s); });
}

}  // namespace

torch::Tensor FusedAdam::step(LossClosure closure) {
  RECORD_FUNCTION("flatnet::fused_adam", std::vector<c10::IValue>());  // for the profiler's tables
  torch::NoGradGuard no_grad;
  torch::Tensor loss = {};
  if (closure != nullptr) {
    at::AutoGradMode enable_grad(true);
    loss = closure();
  }
  std::vector<torch::Tensor> fused;  // the parameters updated here
  bool all_fused = true;
  for (auto& group : param_groups_) {
    auto& options = static_cast<torch::optim::AdamOptions&>(group.options());
    for (auto& p : group.params()) {
      if (!p.grad().defined()) continue;
      const auto key = c10::guts::to_string(p.unsafeGetTensorImpl());
      auto found = state_.find(key);
      if (found == state_.end()) {  // as torch::optim::Adam initialises it
        auto state = std::make_unique<torch::optim::AdamParamState>();
        state->step(0);
        state->exp_avg(torch::zeros_like(p, at::MemoryFormat::Preserve));
        state->exp_avg_sq(torch::zeros_like(p, at::MemoryFormat::Preserve));
        if (options.amsgrad()) state->max_exp_avg_sq(torch::zeros_like(p, at::MemoryFormat::Preserve));
        found = state_.emplace(key, std::move(state)).first;
      }
      auto& state = static_cast<torch::optim::AdamParamState&>(*found->second);
      auto grad = p.grad();
      // Moments read back from a checkpoint are contiguous; a channels-last weight's are made so again.
      for (auto* moment : {&state.exp_avg(), &state.exp_avg_sq()})
        if (moment->defined() && moment->sizes() == p.sizes() && moment->strides() != p.strides())
          *moment = torch::empty_like(p).copy_(*moment);
      if (options.amsgrad() || !one_pass_layout(p, grad, state.exp_avg(), state.exp_avg_sq())) {
        all_fused = false;
        continue;
      }
      fused.push_back(p);
      state.step(state.step() + 1);
      const double beta1 = std::get<0>(options.betas()), beta2 = std::get<1>(options.betas());
      const double bias_correction1 = 1 - std::pow(beta1, state.step());
      const double bias_correction2 = 1 - std::pow(beta2, state.step());
      const AdamScalars scalars{static_cast<float>(beta1),
                                static_cast<float>(beta2),
                                static_cast<float>(options.weight_decay()),
                                static_cast<float>(std::sqrt(bias_correction2)),
                                static_cast<float>(options.eps()),
                                static_cast<float>(options.lr() / bias_correction1)};
      update(p.data_ptr<float>(), grad.data_ptr<float>(), state.exp_avg().data_ptr<float>(),
             state.exp_avg_sq().data_ptr<float>(), p.numel(), scalars);
    }
  }
  one_pass_updates_ = static_cast<int64_t>(fused.size());
  if (!all_fused) {  // the rest by torch::optim::Adam, which skips parameters without a gradient
    std::vector<torch::Tensor> grads;
    for (auto& p : fused) grads.push_back(p.grad()), p.mutable_grad() = torch::Tensor();
    torch::optim::Adam::step();
    for (size_t i = 0; i < fused.size(); ++i) fused[i].mutable_grad() = grads[i];
  }
  return loss;
}

}  // namespace flatnet
