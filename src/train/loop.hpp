#pragma once
// The one training loop every trainer runs (FlatNet's GAN trainer, the mask trainer, the code-pair
// trainer). It owns what they share: the step count (from a resumed step to the last), the
// progress bar and its status line, the wall-clock budget (train.minutes, counting the seconds a
// resumed run trained before), Ctrl-C, the cadence of log rows and of validation + checkpoint, the
// final checkpoint of a run stopped early, and the policy on non-finite values (train/nonfinite.hpp:
// a bad step is skipped, kNonFiniteLimit in a row stop). A trainer says what a step, a log row and
// a checkpoint are (LoopHooks); the loop says when.
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <string>
#include <utility>

namespace flatnet {

// The schedule every trainer shares (the train.* rows iterations, minutes, batch, lr, seed, val_every,
// log_every of train/options.cpp), one struct the three trainers' options and the loop's extend; each
// trainer sets its own defaults in its constructor (its defaults file's, or the thesis's recipe).
struct Schedule {
  int64_t iterations = 1;  // the step the run ends at, when it has no time budget
  // Wall-clock budget of the whole run, resumed parts included (0: none). A budget is the run's
  // length: the run ends when it is spent, whatever `iterations` says (train.minutes alone bounds it).
  double minutes = 0;
  int64_t batch = 4;  // samples per step
  double lr = 1e-4;   // the main optimiser's rate
  uint64_t seed = 0;  // initialisation, data order and augmentation
  int64_t val_every = 500, log_every = 50;
  bool progress = true;
};

struct LoopOptions : Schedule {
  std::string label = "train";  // the progress bar's
  int64_t first_step = 0;       // steps done before this run (a resumed run's)
  double seconds_before = 0;    // seconds the run trained before (resume)
  bool writer = true;           // logs and checkpoints (rank 0 of a data-parallel run; the others only step)
  // For the non-finite error: where the last good state is, and what to change.
  std::string last_good = "nothing was saved";
  std::string remedy = "a lower train.lr";
  // false: the first non-finite step stops the run (data-parallel ranks must take the same steps).
  bool skip_nonfinite = true;
  // Wall-clock minutes between saves (the `save` hook) when no checkpoint came sooner (0: off): a run
  // killed without warning (a session's end, SIGKILL) loses at most this much, however rare its
  // validations are.
  double save_minutes = 0;
};

// The loop's options from a trainer's schedule, with the progress bar's label and where the last
// good state is.
inline LoopOptions loop_schedule(const Schedule& o, std::string label, std::string last_good) {
  LoopOptions lo;
  static_cast<Schedule&>(lo) = o;
  lo.label = std::move(label);
  lo.last_good = std::move(last_good);
  return lo;
}

struct LoopHooks {
  // One step; `step` counts the steps done before it. Throws NonFiniteStep, having changed no
  // parameter, when a loss or gradient is not finite (the loop skips it or stops).
  std::function<void(int64_t step)> step;
  // After each step, taken or skipped (optional): `done` steps are done.
  std::function<void(int64_t done)> advanced;
  // Every log_every steps and at the last (writer only): write the log row; returns the status
  // line shown after the progress bar.
  std::function<std::string(int64_t done)> log;
  // Every val_every steps, at the last, and once when the run stops early (Ctrl-C, the budget;
  // writer only): validate and write the checkpoint. Runs before that step's log row, which may
  // report the validation.
  std::function<void(int64_t done)> checkpoint;
  // Every save_minutes of wall-clock time since the last checkpoint or save (optional; writer only):
  // write the resumable state alone, without validating (a checkpoint resets its clock too).
  std::function<void(int64_t done)> save;
  // Data-parallel runs (optional): whether any rank wants to stop, so that all stop together.
  std::function<bool(bool)> any_rank;
};

struct LoopResult {
  int64_t first_step = 0, last_step = 0;
  double seconds = 0;           // this run's wall-clock time
  bool budget_reached = false;  // stopped by the budget
  bool interrupted = false;     // stopped by Ctrl-C
  int64_t skipped = 0;          // non-finite steps skipped
};

class TrainingLoop {
 public:
  TrainingLoop(LoopOptions options, LoopHooks hooks);
  LoopResult run();
  // Seconds the run has trained, resumed parts included (what the budget and a cosine schedule
  // over it count).
  double trained_seconds() const;
  // Seconds since run() started (this process's share of trained_seconds()).
  double elapsed_seconds() const;

 private:
  bool should_stop();

  LoopOptions opt_;
  LoopHooks hooks_;
  double start_seconds_ = 0;  // steady clock at run()
  bool over_budget_ = false;
  double last_save_seconds_ = 0;  // steady clock at the last checkpoint or save (or run())
};

// The loop of a one-process trainer whose state is one checkpoint file (the mask and code-pair
// trainers): its options' schedule, resumed at `first_step` after `seconds_before` of training, with
// its step, log and checkpoint hooks.
template <class TrainerOptions, class Step, class Log, class Checkpoint>
std::unique_ptr<TrainingLoop> checkpointed_loop(const TrainerOptions& o, std::string label,
                                                const std::filesystem::path& checkpoint_file, int64_t first_step,
                                                double seconds_before, Step step, Log log, Checkpoint checkpoint) {
  auto lo = loop_schedule(o, std::move(label), "the last checkpoint (" + checkpoint_file.string() + ")");
  lo.first_step = first_step;
  lo.seconds_before = seconds_before;
  LoopHooks hooks;
  hooks.step = std::move(step);
  hooks.log = std::move(log);
  hooks.checkpoint = std::move(checkpoint);  // before the same step's log row, and at the end
  return std::make_unique<TrainingLoop>(lo, hooks);
}

}  // namespace flatnet
