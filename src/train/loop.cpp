#include "train/loop.hpp"

#include <chrono>

#include "core/error.hpp"
#include "core/util.hpp"
#include "train/nonfinite.hpp"

namespace flatnet {

namespace {

double now_seconds() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

}  // namespace

TrainingLoop::TrainingLoop(LoopOptions options, LoopHooks hooks) : opt_(std::move(options)), hooks_(std::move(hooks)) {
  require(static_cast<bool>(hooks_.step), "training loop", "needs a step");
  require(opt_.log_every >= 1 && opt_.val_every >= 1, "training loop", "log_every and val_every must be 1 or more");
  require(opt_.save_minutes >= 0, "training loop", "save_minutes must be 0 (off) or more");
  start_seconds_ = now_seconds();
}

double TrainingLoop::elapsed_seconds() const { return now_seconds() - start_seconds_; }

double TrainingLoop::trained_seconds() const { return opt_.seconds_before + elapsed_seconds(); }

bool TrainingLoop::should_stop() {
  over_budget_ = opt_.minutes > 0 && trained_seconds() >= 60.0 * opt_.minutes;
  const bool local = interrupted() || over_budget_;
  return hooks_.any_rank ? hooks_.any_rank(local) : local;
}

LoopResult TrainingLoop::run() {
  const FinishItemOnInterrupt finish_step;  // Ctrl-C ends the step, then the checkpoint below
  start_seconds_ = last_save_seconds_ = now_seconds();
  LoopResult r;
  r.first_step = r.last_step = opt_.first_step;
  const bool by_steps = opt_.minutes <= 0;  // else the budget alone ends the run
  Progress progress(opt_.label, by_steps ? opt_.iterations - opt_.first_step : 0, opt_.progress);
  if (opt_.minutes > 0) progress.set_time_left(60.0 * opt_.minutes - trained_seconds());
  NonFiniteGuard nonfinite(opt_.last_good, opt_.remedy);
  const auto budget_status = [&] {
    return opt_.minutes > 0
               ? " | budget left " + format_duration(std::max(0.0, 60.0 * opt_.minutes - trained_seconds()))
               : std::string();
  };
  int64_t checkpointed = -1;
  bool stopping = false;
  int64_t step = opt_.first_step;
  while ((!by_steps || step < opt_.iterations) && !(stopping = should_stop())) {
    try {
      hooks_.step(step);
      nonfinite.good();
    } catch (const NonFiniteStep& bad) {
      if (!opt_.skip_nonfinite) nonfinite.stop(bad);
      nonfinite.skip(bad);  // throws at the limit
    }
    const int64_t done = ++step;
    if (hooks_.advanced) hooks_.advanced(done);
    progress.tick();
    const bool last = by_steps && done == opt_.iterations;
    if (opt_.writer && hooks_.checkpoint && (done % opt_.val_every == 0 || last)) {
      hooks_.checkpoint(done);
      checkpointed = done;
      last_save_seconds_ = now_seconds();
    } else if (opt_.writer && hooks_.save && opt_.save_minutes > 0 &&
               now_seconds() - last_save_seconds_ >= 60.0 * opt_.save_minutes) {
      hooks_.save(done);
      last_save_seconds_ = now_seconds();
    }
    if (opt_.writer && hooks_.log && (done % opt_.log_every == 0 || last))
      progress.set_status(hooks_.log(done) + budget_status());
  }
  // Ctrl-C or the budget: a final checkpoint, so nothing is lost.
  if (stopping && opt_.writer && hooks_.checkpoint && checkpointed != step) hooks_.checkpoint(step);
  progress.finish();
  r.last_step = step;
  r.seconds = elapsed_seconds();
  r.interrupted = stopping && interrupted();
  r.budget_reached = stopping && over_budget_ && !r.interrupted;
  r.skipped = nonfinite.skipped();
  return r;
}

}  // namespace flatnet
