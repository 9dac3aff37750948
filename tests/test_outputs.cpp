// Runs that cannot hurt (issue 25): outputs never replace what flatnet did not write for that role,
// one command writes a folder at a time, and reruns check what they reuse.
#include "catch_torch.hpp"

#include <fstream>

#include "core/error.hpp"
#include "core/output_dir.hpp"
#include "core/util.hpp"
#include "helpers.hpp"
#include "io/image.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;
using test::q;

namespace {

OutputRole role(const std::string& command, const std::string& settings = "", bool force = false) {
  OutputRole r;
  r.command = command;
  r.settings = settings;
  r.force = force;
  return r;
}

void touch(const std::filesystem::path& p, const std::string& text = "x") { std::ofstream(p) << text; }

}  // namespace

TEST_CASE("output folders: one role each, never a folder of foreign files, --force to override", "[outputs]") {
  test::Scratch s("claims");
  const auto dir = s.dir / "out";
  {
    auto c = claim_output_folder(dir, role("infer", "model a"));
    CHECK_FALSE(c.existed());
    touch(dir / "x.png");
  }
  CHECK(std::filesystem::exists(dir / kOutputMarker));
  CHECK(claim_output_folder(dir, role("infer", "model a")).existed());  // a rerun
  CHECK_THROWS_WITH(claim_output_folder(dir, role("infer", "model b")),
                    Contains(dir.string()) && Contains("other settings") && Contains("add output_role.force") &&
                        !Contains("--force"));  // a library caller is told the option, not a flag
  CHECK_THROWS_WITH(claim_output_folder(dir, role("mask train")),
                    Contains("holds the output of `flatnet infer`") && Contains("output_role.force"));
  CHECK_NOTHROW(claim_output_folder(dir, role("infer", "model b", true)));  // --force re-marks it
  CHECK(claim_output_folder(dir, role("infer", "model b")).existed());
  // A folder of files flatnet did not write (a dataset's gt/, captures, photographs).
  const auto gt = s.dir / "gt";
  std::filesystem::create_directories(gt);
  touch(gt / "img.png");
  CHECK_THROWS_WITH(claim_output_folder(gt, role("infer")),
                    Contains(gt.string()) && Contains("flatnet did not write") && Contains("img.png"));
  CHECK_FALSE(std::filesystem::exists(gt / kOutputMarker));
  // An older flatnet's run folder (no marker) is recognised by its own file.
  const auto old_run = s.dir / "old_run";
  std::filesystem::create_directories(old_run);
  touch(old_run / "latest.ckpt");
  auto train = role("train");
  train.own_file = "latest.ckpt";
  CHECK(claim_output_folder(old_run, train).existed());
  // A file is not a folder.
  touch(s.dir / "file");
  CHECK_THROWS_WITH(claim_output_folder(s.dir / "file", role("infer")), Contains("not a folder"));
}

TEST_CASE("output folders: a second command is refused while one writes, --force or not", "[outputs]") {
  test::Scratch s("locks");
  const auto dir = s.dir / "out";
  auto held = claim_output_folder(dir, role("recon"));
  CHECK_THROWS_WITH(claim_output_folder(dir, role("recon", "", true)),
                    Contains(dir.string()) && Contains("another flatnet command is writing") && Contains("pid"));
  // Another process: the same refusal, exit 2, nothing written.
  const auto r =
      test::run_flatnet("recon --method tikhonov --input " + q(test::data_dir() / "golden" / "bsds_16052_raw.png") +
                        " --out " + q(dir) + " --force");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("another flatnet command is writing"));
  CHECK_FALSE(std::filesystem::exists(dir / "bsds_16052_raw.png"));
  held = OutputClaim();  // released
  CHECK_NOTHROW(claim_output_folder(dir, role("recon")));
}

TEST_CASE("output folders: a folder removed under its command is written no more", "[outputs]") {
  test::Scratch s("removed");
  const auto dir = s.dir / "run";
  auto held = claim_output_folder(dir, role("train"));
  write_text_atomically(dir / "latest.ckpt", "one");
  write_text_atomically(dir / "kept" / "step500.flatnet", "kept");  // a subfolder of the held one
  CHECK(read_file_text(dir / "latest.ckpt", 16) == "one");
  // The user removes the run while it trains: its next write neither re-creates the folder nor writes.
  std::filesystem::remove_all(dir);
  CHECK_THROWS_WITH(write_text_atomically(dir / "best.ckpt", "old run"),
                    Contains(dir.string()) && Contains("was removed, moved or replaced") && Contains("best.ckpt"));
  CHECK_FALSE(std::filesystem::exists(dir));
  // Another run starts in its place (its own lock file): the old command still writes nothing there.
  std::filesystem::create_directories(dir);
  touch(dir / kOutputLock, "pid 1, flatnet train\n");
  touch(dir / "latest.ckpt", "new run");
  CHECK_THROWS_WITH(write_text_atomically(dir / "latest.ckpt", "old run"), Contains("was removed, moved or replaced"));
  CHECK_THROWS(write_text_atomically(dir / "kept" / "step1000.flatnet", "old run"));
  CHECK(read_file_text(dir / "latest.ckpt", 16) == "new run");
  CHECK_FALSE(std::filesystem::exists(dir / "kept"));
  // Files outside every held folder are untouched by the check.
  CHECK_NOTHROW(write_text_atomically(s.dir / "elsewhere.txt", "fine"));
  held = OutputClaim();
  CHECK_NOTHROW(write_text_atomically(dir / "latest.ckpt", "no claim held"));
  // A folder named with a trailing separator (`--out RUN/`) is held the same.
  const auto other = s.dir / "other";
  auto slash = claim_output_folder(other / "", role("train"));
  std::filesystem::remove_all(other);
  CHECK_THROWS_WITH(write_text_atomically(other / "latest.ckpt", "x"), Contains("was removed, moved or replaced"));
  CHECK_FALSE(std::filesystem::exists(other));
}

TEST_CASE("output folders: a command refused on bad input leaves no folder behind", "[outputs]") {
  test::Scratch s("unwind");
  const auto dir = s.dir / "new";
  try {
    auto c = claim_output_folder(dir, role("infer"));
    throw Error("bad input found after the claim");
  } catch (const Error&) {
  }
  CHECK_FALSE(std::filesystem::exists(dir));
  // An existing empty folder stays, without the marker.
  std::filesystem::create_directories(dir);
  try {
    auto c = claim_output_folder(dir, role("infer"));
    throw Error("bad input");
  } catch (const Error&) {
  }
  CHECK(std::filesystem::exists(dir));
  CHECK(std::filesystem::is_empty(dir));
  // A folder removed while its command failed, and claimed again by a new run (only that run's
  // marker and lock in it so far): the failing command's undo leaves the new run's folder alone.
  const auto run = s.dir / "run";
  OutputClaim new_run;
  try {
    auto failing = claim_output_folder(run, role("train"));
    std::filesystem::remove_all(run);
    new_run = claim_output_folder(run, role("train"));
    throw Error("bad input found after the claim");
  } catch (const Error&) {
  }
  CHECK(std::filesystem::exists(run / kOutputMarker));
  CHECK(std::filesystem::exists(run / kOutputLock));
  CHECK_THROWS_WITH(claim_output_folder(run, role("train")), Contains("another flatnet command is writing"));
}

TEST_CASE("outputs never replace inputs: infer into a dataset's gt, patterns into raw captures", "[outputs][cli]") {
  test::Scratch s("no_replace");
  const auto gt = s.dir / "dataset" / "gt", meas = s.dir / "dataset" / "meas";
  std::filesystem::create_directories(gt);
  std::filesystem::create_directories(meas);
  std::filesystem::copy_file(test::data_dir() / "golden" / "bsds_16052_raw.png", meas / "bsds_16052.png");
  std::filesystem::copy_file(test::data_dir() / "golden" / "bsds_16052_scene.png", gt / "bsds_16052.png");
  const auto truth = read_bytes(gt / "bsds_16052.png");
  const auto model = test::source_dir() / "models" / "flatnet-sim-transpose.flatnet";
  auto r = test::run_flatnet("infer --model " + q(model) + " --input " + q(meas) + " --out " + q(gt));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("gt") && Contains("flatnet did not write"));
  CHECK(read_bytes(gt / "bsds_16052.png") == truth);
  r = test::run_flatnet("calibrate --write-patterns " + q(meas));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("meas") && Contains("flatnet did not write"));
  CHECK(read_gray16(meas / "bsds_16052.png").size(0) == 1024);  // still the 16-bit capture
  // Two models into one folder: the second is refused, not mixed in; --force replaces.
  const auto out = s.dir / "rec";
  REQUIRE(test::run_flatnet("infer --precision fp32 --model " + q(model) + " --input " + q(meas) + " --out " + q(out))
              .code == 0);
  const auto calibfree = test::source_dir() / "models" / "flatnet-sim-calibfree.flatnet";
  r = test::run_flatnet("infer --precision fp32 --model " + q(calibfree) + " --input " + q(meas) + " --out " + q(out));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("other settings") && Contains("add --force to write into it anyway") &&
                           !Contains("output_role"));  // the CLI names its flag
  r = test::run_flatnet("infer --precision fp32 --model " + q(calibfree) + " --input " + q(meas) + " --out " + q(out) +
                        " --force");
  CHECK(r.code == 0);
}

TEST_CASE("simulate checks what it reuses: cut captures, empty gt, edited photographs, odd names", "[outputs][cli]") {
  test::Scratch s("sim_reuse");
  const auto src = test::make_photos(s.dir / "photos");
  const std::string cmd = "simulate --images " + q(src) + " --out " + q(s.dir / "ds") + " --val-fraction 0.5";
  REQUIRE(test::run_flatnet(cmd).code == 0);
  const auto meas = s.dir / "ds" / "meas" / "bsds_16052_scene.png";
  const auto gt = s.dir / "ds" / "gt" / "inet_n02980441_castle_scene.png";
  const auto good_meas = read_bytes(meas);
  // A capture cut to 1000 bytes and an empty gt file are made again, not counted as done.
  {
    std::ofstream(meas, std::ios::binary | std::ios::trunc).write(good_meas.data(), 1000);
    std::ofstream(gt, std::ios::trunc);
  }
  auto r = test::run_flatnet(cmd);
  INFO(r.output);
  CHECK(r.code == 0);
  CHECK_THAT(r.output, Contains("simulated 2 captures (0 already done)"));
  CHECK(read_bytes(meas) == good_meas);  // the same capture as before (deterministic noise)
  CHECK(read_rgb(gt).size(1) == 256);
  // A photograph whose content changed: its capture is made again.
  std::filesystem::copy_file(test::data_dir() / "golden" / "inet_n02980441_castle_scene.png",
                             src / "bsds_16052_scene.png", std::filesystem::copy_options::overwrite_existing);
  r = test::run_flatnet(cmd);
  CHECK_THAT(r.output, Contains("simulated 1 captures (1 already done)"));
  CHECK(read_bytes(meas) != good_meas);
  // A name with a line break would break the list files.
  std::filesystem::copy_file(test::data_dir() / "golden" / "bsds_16052_scene.png", src / "two\nlines.png");
  r = test::run_flatnet(cmd);
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("line break"));
}
