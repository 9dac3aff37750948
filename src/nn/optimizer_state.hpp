#pragma once
// Checks of training state read back from a checkpoint, by the rules of what it is, before LibTorch
// sees it: a hand-edited or damaged file must give an error naming the file, never NaN weights, a
// training run that "diverges", or LibTorch's own "Invalid mt19937 state".
#include <filesystem>
#include <string>

#include <torch/torch.h>

namespace flatnet {

// Adam's state for one parameter (Kingma & Ba 2015, Algorithm 1): step t >= 0, the first moment m
// finite, the second raw moment v finite and >= 0 (it is a running mean of g^2; a negative v makes
// sqrt(v_hat) NaN at the next step). `what` names the entry ("optimizer.mask.u.").
void require_adam_moments(int64_t step, const torch::Tensor& exp_avg, const torch::Tensor& exp_avg_sq,
                          const std::filesystem::path& path, const std::string& what);
// Adam's hyper-parameters: betas in [0, 1), eps > 0 and finite, lr and weight decay finite and >= 0.
void require_adam_options(double beta1, double beta2, double eps, double lr, double weight_decay,
                          const std::filesystem::path& path, const std::string& what);
// A state of LibTorch's CPU generator (its mt19937 and normal-sample cache): the right size, and
// accepted by a scratch generator, so the live one is only set from a state known to be valid.
void require_cpu_generator_state(const torch::Tensor& state, const std::filesystem::path& path,
                                 const std::string& what);

}  // namespace flatnet
