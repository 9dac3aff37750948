#pragma once
// Adam as torch::optim::Adam (LibTorch 1.13: the same options, state, checkpoints and update), with
// each parameter's update in one pass over its memory instead of seven ATen operators (mul_, add_,
// mul_, addcmul_, sqrt, div, add_, addcdiv_). A GAN step updates about 100 small tensors, so the
// operators' dispatch and passes were a visible share of a training step (`flatnet bench --rows
// train_cpu --profile 40`). Parameters it cannot take in one pass (amsgrad, sparse, a gradient or
// state in another layout) go through torch::optim::Adam's own update.
#include <torch/torch.h>

namespace flatnet {

class FusedAdam : public torch::optim::Adam {
 public:
  using torch::optim::Adam::Adam;
  torch::Tensor step(LossClosure closure = nullptr) override;
  // How many parameters the last step updated in one pass (the rest went through Adam's own update).
  int64_t one_pass_updates() const { return one_pass_updates_; }

 private:
  int64_t one_pass_updates_ = 0;
};

}  // namespace flatnet
