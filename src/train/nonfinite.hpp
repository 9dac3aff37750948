#pragma once
// One policy on non-finite values for every trainer (GAN, mask, code pair, co-design codes): a step
// whose loss or gradients are not finite changes no parameter and is skipped; kNonFiniteLimit such
// steps in a row stop training with an error that names the step, what was not finite and where
// the last good state is. A single bad step (an SVD with nearly equal singular values, one
// pathological batch) costs one step; a run that has diverged stops at once, with nothing saved
// from the bad steps.
#include <cstdint>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "core/error.hpp"

namespace flatnet {

constexpr int64_t kNonFiniteLimit = 3;

// What a step throws before any parameter changes when a value is not finite.
class NonFiniteStep : public Error {
 public:
  NonFiniteStep(const std::string& what, double value, int64_t step);
  std::string what_was;  // "generator loss (mse 0.02)"
  double value;
  int64_t step;
};

// Whether every tensor (gradients, say) is finite; undefined tensors count as finite.
bool all_finite(const std::vector<torch::Tensor>& tensors);

class NonFiniteGuard {
 public:
  // `last_good`: where the run's last good state is (a checkpoint, or "nothing was saved").
  // `remedy`: the setting to change ("a lower train.lr").
  NonFiniteGuard(std::string last_good, std::string remedy);
  // A finite step: the count of bad steps in a row starts again.
  void good() { in_a_row_ = 0; }
  // A skipped step: counted; throws Error ("training diverged: ...") at the limit.
  void skip(const NonFiniteStep& bad);
  // Stops now (where a step cannot be skipped): the same error as at the limit.
  [[noreturn]] void stop(const NonFiniteStep& bad);
  int64_t skipped() const { return skipped_; }

 private:
  std::string last_good_, remedy_;
  int64_t in_a_row_ = 0, skipped_ = 0;
};

}  // namespace flatnet
