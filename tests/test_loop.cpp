// The one training loop (train/loop.hpp) and the logs it writes through (train/csv_log.hpp).
#include "catch_torch.hpp"

#include <csignal>
#include <fstream>
#include <thread>

#include "core/util.hpp"
#include "helpers.hpp"
#include "train/csv_log.hpp"
#include "train/loop.hpp"
#include "train/nonfinite.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

// A loop's events as text: "s3" the step after 3 done, "c4" a checkpoint after 4, "l4" a log row.
struct Recorder {
  std::vector<std::string> events;
  LoopHooks hooks() {
    LoopHooks h;
    h.step = [this](int64_t step) { events.push_back("s" + std::to_string(step)); };
    h.checkpoint = [this](int64_t done) { events.push_back("c" + std::to_string(done)); };
    h.log = [this](int64_t done) {
      events.push_back("l" + std::to_string(done));
      return std::string();
    };
    return h;
  }
  int64_t count(char kind) const {
    return std::count_if(events.begin(), events.end(), [&](const std::string& e) { return e[0] == kind; });
  }
};

LoopOptions quiet(int64_t iterations, int64_t log_every, int64_t val_every) {
  LoopOptions o;
  o.iterations = iterations, o.log_every = log_every, o.val_every = val_every, o.progress = false;
  return o;
}

}  // namespace

TEST_CASE("training loop: steps from the resumed step, a checkpoint before its log row, both at the last step",
          "[train][loop]") {
  Recorder rec;
  auto o = quiet(7, 2, 3);
  o.first_step = 2;  // resumed after 2 steps
  const auto r = TrainingLoop(o, rec.hooks()).run();
  CHECK(r.first_step == 2);
  CHECK(r.last_step == 7);
  CHECK_FALSE(r.budget_reached);
  CHECK_FALSE(r.interrupted);
  CHECK(rec.events == std::vector<std::string>{"s2", "c3", "s3", "l4", "s4", "s5", "c6", "l6", "s6", "c7", "l7"});
}

TEST_CASE("training loop: saves on the wall clock between rare checkpoints, and none when save_minutes is 0",
          "[train][loop]") {
  for (const double minutes : {0.0, 0.05 / 60}) {  // off, then 50 ms
    Recorder rec;
    auto o = quiet(12, 1000, 6);
    o.save_minutes = minutes;
    auto hooks = rec.hooks();
    hooks.step = [&](int64_t step) {
      rec.events.push_back("s" + std::to_string(step));
      std::this_thread::sleep_for(std::chrono::milliseconds(30));
    };
    hooks.save = [&](int64_t done) { rec.events.push_back("v" + std::to_string(done)); };
    TrainingLoop(o, hooks).run();
    CHECK(rec.count('c') == 2);  // at 6 and 12: a checkpoint is never replaced by a save
    if (minutes == 0) {
      CHECK(rec.count('v') == 0);
    } else {
      // 30 ms steps, a save once 50 ms have passed since the last save or checkpoint: at least one in
      // each checkpoint's interval (every other step; every step on a loaded machine), never at a
      // checkpoint's step.
      CHECK(rec.count('v') >= 2);
      CHECK(rec.count('v') <= 10);
      CHECK(std::find(rec.events.begin(), rec.events.end(), "v6") == rec.events.end());
      CHECK(std::find(rec.events.begin(), rec.events.end(), "v12") == rec.events.end());
    }
  }
}

TEST_CASE("training loop: a process that does not write (data-parallel rank > 0) logs and checkpoints nothing",
          "[train][loop]") {
  Recorder rec;
  auto o = quiet(4, 1, 1);
  o.writer = false;
  TrainingLoop(o, rec.hooks()).run();
  CHECK(rec.events == std::vector<std::string>{"s0", "s1", "s2", "s3"});
}

TEST_CASE("training loop: the time budget stops the run with a final checkpoint and counts resumed time",
          "[train][loop]") {
  Recorder rec;
  auto o = quiet(1000000, 1000, 1000);
  o.minutes = 0.5 / 60;  // half a second
  auto hooks = rec.hooks();
  hooks.step = [&](int64_t) { std::this_thread::sleep_for(std::chrono::milliseconds(20)); };
  const auto r = TrainingLoop(o, hooks).run();
  CHECK(r.budget_reached);
  CHECK(r.last_step > 5);
  CHECK(r.last_step < 100);
  CHECK(r.seconds >= 0.5);
  CHECK(rec.events == std::vector<std::string>{"c" + std::to_string(r.last_step)});  // the final checkpoint
  // A resumed run that already spent its budget takes no step and still leaves a checkpoint.
  Recorder spent;
  o.seconds_before = 60;
  o.first_step = 40;
  const auto again = TrainingLoop(o, spent.hooks()).run();
  CHECK(again.budget_reached);
  CHECK(again.last_step == 40);
  CHECK(spent.events == std::vector<std::string>{"c40"});
}

TEST_CASE("training loop: Ctrl-C ends the current step, then a checkpoint, and the run reports it", "[train][loop]") {
  watch_interrupts();
  Recorder rec;
  auto hooks = rec.hooks();
  hooks.step = [&](int64_t step) {
    if (step == 3) std::raise(SIGINT);  // as a user's Ctrl-C during the fourth step
  };
  const auto r = TrainingLoop(quiet(100, 50, 50), hooks).run();
  const bool was_interrupted = interrupted();
  watch_interrupts();  // clears the flag for the tests that follow
  CHECK(was_interrupted);
  CHECK(r.interrupted);
  CHECK_FALSE(r.budget_reached);
  CHECK(r.last_step == 4);
  CHECK(rec.events == std::vector<std::string>{"c4"});
}

TEST_CASE("training loop: one policy on non-finite steps: skipped, counted, three in a row stop",
          "[train][loop][errors]") {
  // Steps 2 and 5 are bad: both skipped, the run goes on, and every step still counts.
  std::vector<int64_t> advanced;
  LoopHooks hooks;
  int64_t taken = 0;
  hooks.step = [&](int64_t step) {
    if (step == 2 || step == 5) throw NonFiniteStep("loss", std::nan(""), step);
    ++taken;
  };
  hooks.advanced = [&](int64_t done) { advanced.push_back(done); };
  auto r = TrainingLoop(quiet(8, 4, 4), hooks).run();
  CHECK(r.skipped == 2);
  CHECK(taken == 6);
  CHECK(advanced == std::vector<int64_t>{1, 2, 3, 4, 5, 6, 7, 8});
  // kNonFiniteLimit bad steps in a row stop with an error naming the step and the last good state.
  hooks.step = [&](int64_t step) {
    if (step >= 3) throw NonFiniteStep("loss", std::nan(""), step);
  };
  auto o = quiet(100, 10, 10);
  o.last_good = "RUN/latest.ckpt";
  CHECK_THROWS_WITH(TrainingLoop(o, hooks).run(),
                    Contains("step 5") && Contains("RUN/latest.ckpt") && Contains("a lower train.lr"));
  // Data-parallel runs stop at the first.
  o.skip_nonfinite = false;
  CHECK_THROWS_WITH(TrainingLoop(o, hooks).run(), Contains("step 3"));
  // Any other error passes through untouched.
  hooks.step = [&](int64_t) { throw Error("disk full"); };
  CHECK_THROWS_WITH(TrainingLoop(o, hooks).run(), Contains("disk full"));
}

TEST_CASE("training loop: all ranks stop together when one asks", "[train][loop]") {
  Recorder rec;
  auto hooks = rec.hooks();
  int64_t asked = 0;
  hooks.any_rank = [&](bool local) {
    ++asked;
    return local || asked > 3;  // another rank was interrupted before the fourth step
  };
  const auto r = TrainingLoop(quiet(100, 50, 50), hooks).run();
  CHECK(r.last_step == 3);
  CHECK(rec.events == std::vector<std::string>{"s0", "s1", "s2", "c3"});
}

TEST_CASE("a resumed run's CSV log keeps its rows up to the checkpoint, under the current header", "[train][logs]") {
  test::Scratch s("csv_resume");
  const auto path = s.dir / "log.csv";
  std::ofstream(path) << "step,loss\n1,0.5\n2,0.4\n2x,cut\n3,0.3\ngarbage\n4,0.2\n";
  auto log = CsvLog::resume(path, "step,loss,psnr", 3);
  // Rows written before the header gained a column get it empty (not recorded), so every row has the
  // header's columns.
  CHECK(read_file_text(path, 1 << 20) == "step,loss,psnr\n1,0.5,\n2,0.4,\n3,0.3,\n");  // written at once
  log.add(4, 0.25, 19.5);
  log.flush();
  CHECK(read_file_text(path, 1 << 20) == "step,loss,psnr\n1,0.5,\n2,0.4,\n3,0.3,\n4,0.25,19.5\n");
  // No file yet: a fresh log.
  CsvLog::resume(s.dir / "new.csv", "step,psnr", 10);
  CHECK(read_file_text(s.dir / "new.csv", 1 << 20) == "step,psnr\n");
}
