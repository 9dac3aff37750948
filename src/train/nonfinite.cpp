#include "train/nonfinite.hpp"

#include <iostream>
#include <sstream>

namespace flatnet {

namespace {

std::string describe(const std::string& what, double value, int64_t step) {
  std::ostringstream os;
  os << "the " << what << " is " << value << " at step " << step;
  return os.str();
}

}  // namespace

NonFiniteStep::NonFiniteStep(const std::string& what, double value_, int64_t step_)
    : Error(describe(what, value_, step_)), what_was(what), value(value_), step(step_) {}

bool all_finite(const std::vector<torch::Tensor>& tensors) {
  for (const auto& t : tensors)
    if (t.defined() && !torch::isfinite(t).all().item<bool>()) return false;
  return true;
}

NonFiniteGuard::NonFiniteGuard(std::string last_good, std::string remedy)
    : last_good_(std::move(last_good)), remedy_(std::move(remedy)) {}

void NonFiniteGuard::stop(const NonFiniteStep& bad) {
  std::ostringstream os;
  os << "training diverged: " << bad.what() << " (" << std::max<int64_t>(1, in_a_row_)
     << " non-finite step(s) in a row); no optimiser stepped on them and nothing was saved from them; the last "
     << "good state is " << last_good_ << ". Try " << remedy_ << ".";
  throw Error(os.str());
}

void NonFiniteGuard::skip(const NonFiniteStep& bad) {
  ++skipped_;
  if (++in_a_row_ >= kNonFiniteLimit) stop(bad);
  std::cerr << "\nskipped step " << bad.step << ": " << bad.what() << " (" << in_a_row_ << " of " << kNonFiniteLimit
            << " in a row stop training)\n";
}

}  // namespace flatnet
