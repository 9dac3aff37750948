// The flatnet binary end to end: simulate -> recon -> eval, resumability, and bad input.
#include "catch_torch.hpp"
#include <fstream>
#include <unistd.h>

#include <nlohmann/json.hpp>

#include "core/error.hpp"
#include "core/output_dir.hpp"
#include "core/util.hpp"
#include "helpers.hpp"
#include "io/image.hpp"
#include "io/config.hpp"
#include "io/mat.hpp"
#include "nn/model_file.hpp"
#include "bench/bench.hpp"
#include "nn/onednn_conv.hpp"
#include "core/precision.hpp"
#include "optics/camera.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {
using test::kOnDisk;
using test::q;

using test::make_photos;
}  // namespace

TEST_CASE("errors mark the options they name: what() shows the key, a front end renders it its own way", "[cli]") {
  const Error e(option_key("simulate.lamp_gain") + ": must lie in (0, 10000]; see " + option_key("train.batch"));
  CHECK(std::string(e.what()) == "simulate.lamp_gain: must lie in (0, 10000]; see train.batch");
  CHECK(e.render([](const std::string& key) { return "<" + key + ">"; }) ==
        "<simulate.lamp_gain>: must lie in (0, 10000]; see <train.batch>");
  // A key spelled in plain text is text: nothing guesses names (a file called simulate.out stays so).
  CHECK(Error("simulate.out: exists").render([](const std::string&) { return "--out"; }) == "simulate.out: exists");
  CHECK(render_option_keys(std::string("a ") + kOptionMark + "b") ==
        std::string("a ") + kOptionMark + "b");  // unpaired
  CHECK_THROWS_WITH(require_option(false, "recon.batch", "must be at least 1"), "recon.batch: must be at least 1");
  // A user's file name or value is data: marks in it show as an escape and are never rendered.
  const auto hostile = std::string("x") + kOptionMark + "experiment.out" + kOptionMark + "y";
  const Error from_path(std::filesystem::path(hostile), "no such file");
  CHECK(std::string(from_path.what()) == "x\\x1eexperiment.out\\x1ey: no such file");
  CHECK(from_path.render([](const std::string&) { return "--out"; }) == from_path.what());
  // A label the code wrote is text, and its marks are kept: Error(option_key(k), reason) names k.
  CHECK(Error(option_key("recon.require_fit"), "6 of 6 captures do not fit").render([](const std::string&) {
    return "--require-fit";
  }) == "--require-fit: 6 of 6 captures do not fit");
  CHECK_THROWS_WITH(require(false, option_key("recon.out"), "is the input"), "recon.out: is the input");
  CHECK_THROWS_WITH(require(false, std::filesystem::path(hostile), "is the input"),
                    "x\\x1eexperiment.out\\x1ey: is the input");
  CHECK_THROWS_WITH(Config::load({}, {"train.lr=" + hostile}),
                    Contains("train.lr = x\\x1eexperiment.out\\x1ey is not"));
  CHECK_THROWS_WITH(Config::load({}, {hostile + "=1"}), Contains("unknown setting 'x\\x1eexperiment.out\\x1ey'"));
}

TEST_CASE("train's flags come from its option rows: --iterations, --minutes, --batch, --lr, --precision", "[cli]") {
  test::Scratch s("train_flags");
  const auto help = test::run_flatnet("train --help");
  REQUIRE(help.code == 0);
  CHECK_THAT(help.output, Contains("--minutes") && Contains("train.minutes: wall-clock budget") &&
                              Contains("--precision") && Contains("train.precision: auto"));
  const std::string train =
      "train --config " + q(test::source_dir() / "configs" / "sim_transpose.yaml") + " --out " + q(s.dir / "run");
  // A flag's value is checked by its row's range, and an error names the flag the user typed.
  auto r = test::run_flatnet(train + " --batch 0");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("train.batch = 0 is out of range: 1 to 4096 samples"));  // the row's range
  r = test::run_flatnet(train + " --precision fp16");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--precision: expected auto, fp32 or bf16, got 'fp16'"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "run" / "latest.ckpt"));
  r = test::run_flatnet(train + " --iterations 1e99");  // the flag sets its row's key
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("train.iterations = 1e99 is out of range"));
  // --set comes last and wins over a flag, as in `mask separable`.
  r = test::run_flatnet(train + " --batch 2 --set train.batch=0");
  CHECK_THAT(r.output, Contains("train.batch = 0 is out of range"));
}

TEST_CASE("simulate, recon and eval end to end, and simulate resumes deterministically", "[cli][e2e][slow]") {
  test::Scratch s("e2e");
  auto photos = make_photos(s.dir / "photos");
  auto r = test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "ds") +
                             " --val-fraction 0.5 --seed 3");
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK(read_lines(s.dir / "ds" / "train_meas.txt").size() == 1);
  CHECK(read_lines(s.dir / "ds" / "val_gt.txt").size() == 1);
  REQUIRE(std::filesystem::exists(s.dir / "ds" / "meas" / "bsds_16052_scene.png"));

  auto again = test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "ds") +
                                 " --val-fraction 0.5 --seed 3");
  CHECK_THAT(again.output, Contains("simulated 0 captures (2 already done)"));
  // Other settings never mix into a dataset: refused by name, or rebuilt with --force.
  const auto before = read_lines(s.dir / "ds" / "train_meas.txt");
  auto mixed = test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "ds") +
                                 " --val-fraction 0.5 --seed 4");
  CHECK(mixed.code == 2);
  CHECK_THAT(mixed.output, Contains("seed 3 -> 4") && Contains("--force"));
  std::filesystem::create_directories(s.dir / "other_photos");
  std::filesystem::copy(photos / "bsds_16052_scene.png", s.dir / "other_photos" / "bsds_16052_scene.png");
  mixed = test::run_flatnet("simulate --images " + q(s.dir / "other_photos") + " --out " + q(s.dir / "ds") +
                            " --val-fraction 0.5 --seed 3");
  CHECK(mixed.code == 2);
  CHECK_THAT(mixed.output, Contains("images "));
  CHECK(read_lines(s.dir / "ds" / "train_meas.txt") == before);
  auto rebuilt = test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "ds3") +
                                   " --val-fraction 0.5 --seed 3 --noise off");
  REQUIRE(rebuilt.code == 0);
  rebuilt = test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "ds3") +
                              " --val-fraction 0.5 --seed 3 --force");
  INFO(rebuilt.output);
  CHECK(rebuilt.code == 0);
  CHECK_THAT(rebuilt.output, Contains("simulated 2 captures (0 already done)"));
  auto other = test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "ds2") +
                                 " --val-fraction 0.5 --seed 3 --workers 1");
  REQUIRE(other.code == 0);
  auto bytes = [](const std::filesystem::path& p) {
    std::ifstream f(p, std::ios::binary);
    return std::string(std::istreambuf_iterator<char>(f), {});
  };
  CHECK(bytes(s.dir / "ds" / "meas" / "bsds_16052_scene.png") ==
        bytes(s.dir / "ds2" / "meas" / "bsds_16052_scene.png"));

  r = test::run_flatnet("recon --method tikhonov --input " + q(s.dir / "ds" / "meas") + " --out " +
                        q(s.dir / "rec" / "tikhonov"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("ms per capture"));
  r = test::run_flatnet("eval --gt " + q(s.dir / "ds" / "gt") + " --out " + q(s.dir / "rec"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK(std::filesystem::exists(s.dir / "rec" / "sheet.png"));
  // header; per image the method's row and the ground truth's NIQE; the two means
  CHECK(read_lines(s.dir / "rec" / "metrics.csv").size() == 7);
  CHECK_THAT(r.output, Contains("NIQE") && Contains("ground truth"));
  r = test::run_flatnet("eval --niqe none --gt " + q(s.dir / "ds" / "gt") + " --out " + q(s.dir / "rec"));
  REQUIRE(r.code == 0);
  CHECK(read_lines(s.dir / "rec" / "metrics.csv").size() == 4);  // header, 2 images, mean
  CHECK(r.output.find("NIQE") == std::string::npos);
}

TEST_CASE("bad input: one clear line, exit code 2", "[cli][errors]") {
  test::Scratch s("bad");
  std::filesystem::create_directories(s.dir / "empty");

  // Absurd numbers are refused where flags are parsed, in every command, naming the flag.
  const auto golden_raw = test::data_dir() / "golden" / "bsds_16052_raw.png";
  for (const std::string& flags :
       std::vector<std::string>{"--threads 100000", "--batch 0", "--lambda 0", "--lambda -1", "--lambda 1e9"}) {
    INFO(flags);
    const auto bad = test::run_flatnet("recon --method tikhonov --input " + q(golden_raw) + " --out " +
                                       q(s.dir / "rec") + " " + flags);
    CHECK(bad.code == 2);
    CHECK_THAT(bad.output, Contains(flags.substr(0, flags.find(' '))) && Contains("out of range"));
  }
  CHECK_FALSE(std::filesystem::exists(s.dir / "rec"));
  const auto avg = test::run_flatnet("calibrate --rig " + q(test::source_dir() / "configs" / "cameras" / "sim.yaml") +
                                     " --average 0 --out " + q(s.dir / "c.mat"));
  CHECK(avg.code == 2);
  CHECK_THAT(avg.output, Contains("--average"));

  auto r = test::run_flatnet("simulate --images " + q(s.dir / "empty") + " --out " + q(s.dir / "o"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("empty") && Contains("no images"));

  // a calibration without P1r
  std::map<std::string, torch::Tensor> vars;
  for (const char* c : {"b", "gb", "gr"}) {
    vars[std::string("P1") + c] = torch::zeros({500, 256}, torch::kFloat64);
    vars[std::string("Q1") + c] = torch::zeros({620, 256}, torch::kFloat64);
  }
  write_mat(s.dir / "nor.mat", vars);
  auto golden = test::data_dir() / "golden" / "bsds_16052_raw.png";
  r = test::run_flatnet("recon --calib " + q(s.dir / "nor.mat") + " --input " + q(golden) + " --out " + q(s.dir / "o"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("nor.mat") && Contains("missing variable 'P1r'"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "o"));

  // a calibration whose shape does not match the camera's crop
  vars["P1r"] = torch::zeros({480, 256}, torch::kFloat64);
  vars["Q1r"] = torch::zeros({620, 256}, torch::kFloat64);
  write_mat(s.dir / "shape.mat", vars);
  r = test::run_flatnet("recon --calib " + q(s.dir / "shape.mat") + " --input " + q(golden) + " --out " +
                        q(s.dir / "o"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("P1b is 500x256") || Contains("P1r is 480x256"));

  // an 8-bit RGB image where a raw capture is expected
  r = test::run_flatnet("recon --input " + q(test::data_dir() / "golden" / "bsds_16052_scene.png") + " --out " +
                        q(s.dir / "o"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("bsds_16052_scene.png") && Contains("single-channel"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "o" / "bsds_16052_scene.png"));

  r = test::run_flatnet("recon --method wiener --input " + q(golden) + " --out " + q(s.dir / "o"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("tikhonov or tv"));

  r = test::run_flatnet("eval --gt " + q(s.dir / "empty") + " --out " + q(s.dir / "empty"));
  CHECK(r.code == 2);

  r = test::run_flatnet("frobnicate");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("unknown command"));

  std::ofstream(s.dir / "cam.yaml") << "crop: [6, 10, 600, 620]\n";
  r = test::run_flatnet("recon --camera " + q(s.dir / "cam.yaml") + " --input " + q(golden) + " --out " +
                        q(s.dir / "o"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("cam.yaml") && Contains("crop"));

  // Config numbers are checked once, where the config is loaded, before anything is written.
  const std::string train =
      "train --config " + q(test::source_dir() / "configs" / "sim_transpose.yaml") + " --out " + q(s.dir / "run");
  for (const auto& [set, message] : std::vector<std::pair<std::string, std::string>>{
           {"train.lr=nan", "train.lr = nan is not a finite decimal number"},
           {"train.iterations=1e99", "train.iterations = 1e99 is out of range"},
           {"train.workers=100000", "train.workers = 100000 is out of range"},
           {"train.batch=0", "train.batch = 0 is out of range"},
           {"loss.mse=-1", "loss.mse = -1 is out of range"}}) {
    INFO(set);
    r = test::run_flatnet(train + " --set " + set);
    CHECK(r.code == 2);
    CHECK_THAT(r.output, Contains(message) && Contains("--set"));
    CHECK_FALSE(std::filesystem::exists(s.dir / "run"));
  }
  // A batch the machine's memory cannot hold is refused before it is tried; hex is not a number.
  r = test::run_flatnet(train + " --set train.batch=4096 --set data.images=" + q(make_photos(s.dir / "photos")));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("train.batch") && Contains("GB available"));
  // The pre-processor runs on the whole 500x620 window: at width 256 and depth 64 (both inside their
  // ranges) one sample needs over 100 GB. Refused up front, naming it, with no run folder left.
  r = test::run_flatnet(train +
                        " --set train.batch=1 --set model.preprocessor.width=256 --set model.preprocessor.depth=64"
                        " --set data.images=" +
                        q(s.dir / "photos"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("GB available") && Contains("model.preprocessor.width"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "run"));
  r = test::run_flatnet(train + " --set train.batch=0x10");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("train.batch = 0x10 is not a finite decimal number"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "run"));
  // A flag value of the wrong type names the flag.
  r = test::run_flatnet("recon --method tikhonov --lambda nan --input " + q(golden) + " --out " + q(s.dir / "o"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--lambda: 'nan' is not a finite decimal number"));
  r = test::run_flatnet("simulate --images x --out y --val-fraction=half");
  CHECK_THAT(r.output, Contains("--val-fraction: 'half' is not a finite decimal number"));
  r = test::run_flatnet("simulate --images x --out y --limit=2.5");
  CHECK_THAT(r.output, Contains("--limit: '2.5' is not a whole number"));
  r = test::run_flatnet("simulate --images x --out y --seed=-3");
  CHECK_THAT(r.output, Contains("--seed: '-3' is negative"));
  r = test::run_flatnet("simulate --images x --out y --noise=loud");
  CHECK_THAT(r.output, Contains("--noise: 'loud': must be on or off"));
  // A library error names the option's key; the command shows its flag (no text is searched for names).
  r = test::run_flatnet("simulate --images x --out y --lamp-gain -1");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--lamp-gain: must lie in (0, 10000]") && !Contains("simulate.lamp_gain"));
  // A folder of raw captures given to eval as reconstructions: refused, not scored.
  std::filesystem::create_directories(s.dir / "gt_one");
  std::filesystem::create_directories(s.dir / "raw_one");
  std::filesystem::copy_file(test::data_dir() / "golden" / "bsds_16052_scene.png", s.dir / "gt_one" / "bsds_16052.png");
  std::filesystem::copy_file(golden, s.dir / "raw_one" / "bsds_16052.png");
  r = test::run_flatnet("eval --gt " + q(s.dir / "gt_one") + " --out " + q(s.dir / "raw_one"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("not a reconstruction of that scene"));
  r = test::run_flatnet("train --config " + q(s.dir / "empty") + " --out " + q(s.dir / "run"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("is a folder"));
  // A filesystem failure reads as one of flatnet's own errors: the path, then the reason.
  r = test::run_flatnet("recon --input " + q(golden) + " --out " + q(s.dir / "cam.yaml" / "sub"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("cam.yaml/sub: Not a directory"));
  CHECK(r.output.find("filesystem error") == std::string::npos);
}

TEST_CASE("train, export, import and infer from the command line, and bad input is refused", "[cli][train][slow]") {
  test::Scratch s("train_cli");
  auto photos = make_photos(s.dir / "photos");
  REQUIRE(
      test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "ds") + " --val-fraction 0.5").code ==
      0);
  const std::string base = "train --config " + q(test::source_dir() / "configs" / "sim_transpose.yaml") +
                           " --set data.dataset=" + q(s.dir / "ds") + " --set model.unet.width=2" + kOnDisk;
  auto r = test::run_flatnet(base + " --set train.iterations=2 --set train.val_every=1 --out " + q(s.dir / "run"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("model: "));
  const auto model = s.dir / "run" / "model.flatnet";
  REQUIRE(std::filesystem::exists(model));

  // A run folder is never overwritten; --resume continues it.
  auto again = test::run_flatnet(base + " --out " + q(s.dir / "run"));
  CHECK(again.code == 2);
  CHECK_THAT(again.output, Contains("--resume"));
  // --resume keeps the run's own config: another --config is refused, not silently ignored, and
  // the refused resume changes nothing in the folder.
  const auto config_before = read_bytes(s.dir / "run" / "config.yaml");
  auto other_config = test::run_flatnet("train --out " + q(s.dir / "run") + " --resume --config " +
                                        q(test::source_dir() / "configs" / "sim_calibfree.yaml"));
  CHECK(other_config.code == 2);
  CHECK_THAT(other_config.output, Contains("--resume continues with the run's own config") &&
                                      Contains("model.inversion.init") && Contains("--config: ") &&
                                      Contains("with --set key=value") && !Contains("experiment."));
  CHECK(read_bytes(s.dir / "run" / "config.yaml") == config_before);
  auto wider = test::run_flatnet("train --out " + q(s.dir / "run") + " --resume --set model.unet.width=4");
  CHECK(wider.code == 2);
  CHECK(read_bytes(s.dir / "run" / "config.yaml") == config_before);
  // best.ckpt was picked on display validation: resuming under another validation is refused (its
  // next validation would overwrite that model), with the fork's recipe.
  auto judged = test::run_flatnet("train --out " + q(s.dir / "run") + " --resume --set data.val_light=judged");
  CHECK(judged.code == 2);
  CHECK_THAT(judged.output, Contains("data.val_light") && Contains("best.ckpt") && Contains("fork the run"));
  CHECK(read_bytes(s.dir / "run" / "config.yaml") == config_before);
  // Judged validation lights photographs through a rig: a dataset's pairs cannot be relit.
  auto judged_dataset = test::run_flatnet(base + " --set data.val_light=judged --set train.iterations=1 --out " +
                                          q(s.dir / "judged_dataset"));
  CHECK(judged_dataset.code == 2);
  CHECK_THAT(judged_dataset.output, Contains("data.val_light") && Contains("data.source: simulate"));
  auto erring_dataset = test::run_flatnet(base + " --set data.calibration_error=0.03 --set train.iterations=1 --out " +
                                          q(s.dir / "judged_dataset"));
  CHECK(erring_dataset.code == 2);
  CHECK_THAT(erring_dataset.output, Contains("data.calibration_error") && Contains("data.source: simulate"));
  auto unknown_light = test::run_flatnet(base + " --set data.val_light=bright --set train.iterations=1 --out " +
                                         q(s.dir / "judged_dataset"));
  CHECK(unknown_light.code == 2);
  CHECK_THAT(unknown_light.output, Contains("data.val_light") && Contains("must be display or judged, got 'bright'"));
  // A fresh run into a folder left by a run killed before its first checkpoint: refused, or
  // started afresh with --force.
  std::filesystem::create_directories(s.dir / "dead");
  REQUIRE(
      test::run_flatnet(base + " --set train.iterations=1 --set train.val_every=1 --out " + q(s.dir / "dead")).code ==
      0);
  std::filesystem::remove(s.dir / "dead" / "latest.ckpt");
  auto fresh = test::run_flatnet(base + " --set train.iterations=1 --out " + q(s.dir / "dead"));
  CHECK(fresh.code == 2);
  CHECK_THAT(fresh.output, Contains("never reached its first checkpoint") && Contains("--force"));
  // The old run's kept models go too (export --average-of would mix two runs), and a kept/ that is a
  // link is removed as a link: the folder it points to is not the run's and keeps its files.
  std::filesystem::create_directories(s.dir / "dead" / "kept");
  test::write_file(s.dir / "dead" / "kept" / "step2.flatnet", "the old run's model");
  fresh = test::run_flatnet(base + " --set train.iterations=1 --set train.val_every=1 --out " + q(s.dir / "dead") +
                            " --force");
  CHECK(fresh.code == 0);
  CHECK(read_lines(s.dir / "dead" / "val.csv").size() == 2);  // header and this run's one row
  CHECK_FALSE(std::filesystem::exists(s.dir / "dead" / "kept" / "step2.flatnet"));
  std::filesystem::create_directories(s.dir / "elsewhere");
  test::write_file(s.dir / "elsewhere" / "step2.flatnet", "not the run's");
  std::filesystem::remove_all(s.dir / "dead" / "kept");
  std::filesystem::create_directory_symlink(s.dir / "elsewhere", s.dir / "dead" / "kept");
  fresh = test::run_flatnet(base + " --set train.iterations=2 --set train.val_every=1 --set train.keep_every=1 --out " +
                            q(s.dir / "dead") + " --force");
  INFO(fresh.output);
  CHECK(fresh.code == 0);
  CHECK_FALSE(std::filesystem::is_symlink(s.dir / "dead" / "kept"));
  CHECK(std::filesystem::exists(s.dir / "dead" / "kept" / "step2.flatnet"));
  CHECK(test::read_file(s.dir / "elsewhere" / "step2.flatnet") == "not the run's");
  CHECK_FALSE(std::filesystem::exists(s.dir / "elsewhere" / "step1.flatnet"));
  // Another run's checkpoint copied in: refused, naming both runs and --force; the folder unchanged.
  const auto own_checkpoint = read_bytes(s.dir / "run" / "latest.ckpt");
  std::filesystem::copy_file(s.dir / "dead" / "latest.ckpt", s.dir / "run" / "latest.ckpt",
                             std::filesystem::copy_options::overwrite_existing);
  auto mixed = test::run_flatnet("train --out " + q(s.dir / "run") + " --resume --set train.iterations=2");
  CHECK(mixed.code == 2);
  CHECK_THAT(mixed.output, Contains("latest.ckpt") && Contains("belongs to another run") && Contains("--force"));
  CHECK(read_bytes(s.dir / "run" / "config.yaml") == config_before);
  test::write_file(s.dir / "run" / "latest.ckpt", std::string(own_checkpoint.begin(), own_checkpoint.end()));
  // ... and another run's best.ckpt (resume would take its best PSNR): refused the same way.
  if (std::filesystem::exists(s.dir / "run" / "best.ckpt") && std::filesystem::exists(s.dir / "dead" / "best.ckpt")) {
    const auto own_best = read_bytes(s.dir / "run" / "best.ckpt");
    std::filesystem::copy_file(s.dir / "dead" / "best.ckpt", s.dir / "run" / "best.ckpt",
                               std::filesystem::copy_options::overwrite_existing);
    auto mixed_best = test::run_flatnet("train --out " + q(s.dir / "run") + " --resume --set train.iterations=2");
    CHECK(mixed_best.code == 2);
    CHECK_THAT(mixed_best.output, Contains("best.ckpt") && Contains("belongs to another run"));
    test::write_file(s.dir / "run" / "best.ckpt", std::string(own_best.begin(), own_best.end()));
  } else {
    FAIL("both runs validate at step 1, so both hold a best.ckpt");
  }
  // --force=false is no --force: the run is kept (scripts write --force=$FORCE).
  auto kept = test::run_flatnet(base + " --set train.iterations=1 --out " + q(s.dir / "run") + " --force=false");
  CHECK(kept.code == 2);
  CHECK(read_bytes(s.dir / "run" / "latest.ckpt") == own_checkpoint);
  // A log row cut short (a crash while writing) does not block the resume.
  std::ofstream(s.dir / "run" / "log.csv", std::ios::app) << "2,0.5,0.";
  std::ofstream(s.dir / "run" / "log.csv", std::ios::app) << "\ngarbage\n";
  auto more = test::run_flatnet("train --out " + q(s.dir / "run") + " --resume --set train.iterations=3");
  INFO(more.output);
  CHECK(more.code == 0);
  CHECK_THAT(more.output, Contains("steps 2..3") && Contains("dropped 1 malformed row(s)"));
  for (const auto& line : read_lines(s.dir / "run" / "log.csv")) CHECK(line != "garbage");

  // Ctrl-C: exit 130 after the current step, with a checkpoint to resume from.
  const auto stopped = s.dir / "stopped";
  const auto cmd = std::string(FLATNET_BINARY) + " " + base +
                   " --set train.iterations=100000 --set train.log_every=1 --out " + q(stopped) + " > " +
                   q(s.dir / "stopped.log") + " 2>&1 & P=$!; for i in $(seq 300); do [ -s " + q(stopped / "log.csv") +
                   " ] && break; sleep 0.1; done; kill -INT $P; wait $P";
  CHECK(test::run_shell("bash -c " + q(cmd)).code == 130);
  const auto stop_log = read_lines(s.dir / "stopped.log");
  CHECK_THAT(stop_log.empty() ? "" : stop_log.back(), Contains("--resume"));
  CHECK(std::filesystem::exists(stopped / "latest.ckpt"));
  int64_t done = -1;  // "steps 0..K in ..."
  for (const auto& line : stop_log)
    if (line.rfind("steps 0..", 0) == 0) done = std::stoll(line.substr(9));
  REQUIRE(done >= 0);
  // A second SIGTERM ends the process at once (the first asks for a clean stop, which may take a while).
  const auto twice = s.dir / "twice";
  const auto kill_twice = std::string(FLATNET_BINARY) + " " + base +
                          " --set train.iterations=100000 --set train.log_every=1 --out " + q(twice) +
                          " > /dev/null 2>&1 & P=$!; for i in $(seq 300); do [ -s " + q(twice / "log.csv") +
                          " ] && break; sleep 0.1; done; kill -TERM $P; sleep 0.2; kill -TERM $P; wait $P";
  CHECK(test::run_shell("bash -c " + q(kill_twice)).code == 128 + 15);
  auto resumed =
      test::run_flatnet("train --out " + q(stopped) + " --resume --set train.iterations=" + std::to_string(done + 1));
  INFO(resumed.output);
  CHECK(resumed.code == 0);
  CHECK_THAT(resumed.output, Contains("steps " + std::to_string(done) + ".." + std::to_string(done + 1)));

  r = test::run_flatnet("infer --model " + q(model) + " --input " + q(s.dir / "ds" / "meas") + " --out " +
                        q(s.dir / "rec"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK(std::filesystem::exists(s.dir / "rec" / "bsds_16052_scene.png"));
  CHECK_THAT(r.output, Contains("images/s"));
  // Test-time adaptation: a few steps on two of the captures, then every capture reconstructed.
  r = test::run_flatnet("infer --model " + q(model) + " --input " + q(s.dir / "ds" / "meas") + " --out " +
                        q(s.dir / "rec-adapted") + " --adapt-steps 2 --adapt-captures 2");
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("adaptation: adapted to 2 captures in 2 steps"));
  CHECK(std::filesystem::exists(s.dir / "rec-adapted" / "bsds_16052_scene.png"));
  r = test::run_flatnet("infer --model " + q(model) + " --input " + q(s.dir / "ds" / "meas") + " --out " +
                        q(s.dir / "x") + " --adapt-steps 2 --adapt-lr 0");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--adapt-lr"));

  // export -> state dict -> import -> infer gives the same images.
  REQUIRE(test::run_flatnet("export --model " + q(model) + " --state-dict --out " + q(s.dir / "sd.pt")).code == 0);
  // Existing files are kept unless --force, and the file being read is never replaced.
  const auto sd_bytes = read_bytes(s.dir / "sd.pt");
  r = test::run_flatnet("export --model " + q(model) + " --state-dict --out " + q(s.dir / "sd.pt"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("already exists") && Contains("--force"));
  CHECK(read_bytes(s.dir / "sd.pt") == sd_bytes);
  CHECK(test::run_flatnet("export --model " + q(model) + " --state-dict --force --out " + q(s.dir / "sd.pt")).code ==
        0);
  const auto ckpt_bytes = read_bytes(s.dir / "run" / "latest.ckpt");
  r = test::run_flatnet("export --checkpoint " + q(s.dir / "run" / "latest.ckpt") + " --force --out " +
                        q(s.dir / "run" / "latest.ckpt"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("is also the input"));
  CHECK(read_bytes(s.dir / "run" / "latest.ckpt") == ckpt_bytes);
  r = test::run_flatnet("import --state-dict " + q(s.dir / "sd.pt") + " --config " +
                        q(test::source_dir() / "configs" / "sim_transpose.yaml") + " --set model.unet.width=2 --out " +
                        q(s.dir / "imported.flatnet"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  REQUIRE(test::run_flatnet("infer --model " + q(s.dir / "imported.flatnet") + " --input " +
                            q(s.dir / "ds" / "val_meas.txt") + " --out " + q(s.dir / "rec2"))
              .code == 0);
  const auto name = read_lines(s.dir / "ds" / "val_meas.txt").at(0);
  const auto file = std::filesystem::path(name).filename();
  auto bytes = [](const std::filesystem::path& p) {
    std::ifstream f(p, std::ios::binary);
    return std::string(std::istreambuf_iterator<char>(f), {});
  };
  CHECK(bytes(s.dir / "rec" / file) == bytes(s.dir / "rec2" / file));

  // ONNX: export, then the LibTorch-free engine gives the same images (8-bit rounding aside).
  r = test::run_flatnet("export --model " + q(model) + " --onnx " + q(s.dir / "m.onnx"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("checked by ONNX's checker"));
  r = test::run_flatnet("export --model " + q(model) + " --onnx " + q(s.dir / "m.onnx"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("already exists"));
  r = test::run_flatnet("infer --engine opencv --model " + q(s.dir / "m.onnx") + " --input " +
                        q(s.dir / "ds" / "val_meas.txt") + " --out " + q(s.dir / "rec3"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("OpenCV DNN"));
  CHECK((read_rgb(s.dir / "rec" / file) - read_rgb(s.dir / "rec3" / file)).abs().max().item<double>() <= 1.5 / 255);
  const auto not_onnx = test::run_flatnet("infer --engine opencv --model " + q(model) + " --input " +
                                          q(s.dir / "ds" / "meas") + " --out " + q(s.dir / "x"));
  CHECK(not_onnx.code == 2);
  CHECK_THAT(not_onnx.output, Contains("model.flatnet") && Contains("not an ONNX model"));

  // Bad input: exit code 2, a message that says what is wrong.
  auto bad = test::run_flatnet(base + " --set train.itrations=3 --out " + q(s.dir / "bad"));
  CHECK(bad.code == 2);
  CHECK_THAT(bad.output, Contains("train.itrations") && Contains("did you mean 'train.iterations'"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "bad"));
  bad = test::run_flatnet(base + " --set loss.perceptual=1.2 --set loss.vgg_file=" + q(s.dir / "none.pt") + " --out " +
                          q(s.dir / "bad"));
  CHECK(bad.code == 2);
  CHECK_THAT(bad.output, Contains("loss.perceptual = 0"));
  bad = test::run_flatnet("infer --model " + q(s.dir / "run" / "latest.ckpt") + " --input " + q(s.dir / "ds" / "meas") +
                          " --out " + q(s.dir / "x"));
  CHECK(bad.code == 2);
  CHECK_THAT(bad.output, Contains("flatnet export --checkpoint"));
  std::ofstream(s.dir / "small.yaml") << "name: small\ncrop: [0, 0, 400, 620]\n";
  bad = test::run_flatnet("infer --model " + q(model) + " --camera " + q(s.dir / "small.yaml") + " --input " +
                          q(s.dir / "ds" / "meas") + " --out " + q(s.dir / "x"));
  CHECK(bad.code == 2);
  CHECK_THAT(bad.output, Contains("do not match the model"));
  std::filesystem::create_directories(s.dir / "empty");
  bad = test::run_flatnet(base + " --set data.dataset=" + q(s.dir / "empty") + " --out " + q(s.dir / "bad"));
  CHECK(bad.code == 2);
  CHECK_FALSE(std::filesystem::exists(s.dir / "bad"));
}

TEST_CASE("the shipped models run on FlatNet's real prototype captures", "[cli][flatnet-data][solo]") {
  const auto data = test::shared_dir() / "data" / "flatnet";
  const auto model = test::source_dir() / "models" / "flatnet-sim-calibfree.flatnet";
  if (!std::filesystem::exists(data / "fc_6.png") || !std::filesystem::exists(model)) {
    SKIP_TEST("no ../shared/data/flatnet captures or no shipped model");
  }
  test::Scratch s("prototype");
  auto r = test::run_flatnet("infer --model " + q(model) + " --camera " +
                             q(test::source_dir() / "configs" / "cameras" / "flatnet_prototype_level.yaml") +
                             " --input " + q(data / "fc_*.png") + " --out " + q(s.dir / "rec"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("4 captures"));
  for (const char* n : {"fc_6.png", "fc_7.png", "fc_8.png", "fc_9.png"}) {
    const auto img = read_rgb(s.dir / "rec" / n);
    CHECK(img.sizes() == torch::IntArrayRef({3, 256, 256}));
    CHECK(img.std().item<double>() > 0.01);  // an image, not a constant
  }
}

TEST_CASE("distributed training from the command line: two local ranks, resume, and a rank that dies",
          "[cli][dist][slow]") {
  test::Scratch s("dist_cli");
  auto photos = make_photos(s.dir / "photos");
  REQUIRE(
      test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "ds") + " --val-fraction 0.5").code ==
      0);
  const std::string config = q(test::source_dir() / "configs" / "sim_transpose.yaml");
  const std::string sets = " --set data.dataset=" + q(s.dir / "ds") +
                           " --set model.unet.width=2 --set train.val_count=1 --set train.check_sync_every=1" + kOnDisk;
  const std::string launch = "MASTER_PORT=" + std::to_string(21000 + ::getpid() % 20000) +
                             " FLATNET_BIN=" + std::string(FLATNET_BINARY) + " bash " +
                             q(test::source_dir() / "scripts" / "launch_local.sh") + " 2 " + config;
  const auto run = test::run_shell;
  auto r = run(launch + " --out " + q(s.dir / "run") + sets + " --set train.iterations=3 --set train.val_every=3");
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("steps 0..3"));
  CHECK(std::filesystem::exists(s.dir / "run" / "latest.ckpt"));
  CHECK_THAT(read_lines(s.dir / "run.rank1.log").back(), Contains("rank 1: steps 0..3 done"));

  r = run(launch + " --out " + q(s.dir / "run") + " --resume --set train.iterations=4");
  INFO(r.output);
  CHECK(r.code == 0);
  CHECK_THAT(r.output, Contains("steps 3..4"));

  // Rank 1 is killed mid-run: rank 0 stops with a clear error instead of waiting forever. The kill
  // waits on an event, not a clock: rank 0's first logged step (both ranks past the rendezvous), or
  // rank 0's end. What bounds rank 0's wait is its own --dist-timeout; a hang is CTest's to end.
  const std::string env =
      "WORLD_SIZE=2 MASTER_ADDR=127.0.0.1 MASTER_PORT=" + std::to_string(22000 + ::getpid() % 20000);
  const std::string train = std::string(FLATNET_BINARY) + " train --config " + config + " --threads 1 --out " +
                            q(s.dir / "dead") + sets +
                            " --set train.iterations=100000 --set train.log_every=1 --dist-timeout 60";
  const std::string first_step = "[ \"$(wc -l < " + q(s.dir / "dead" / "log.csv") + " 2>/dev/null)\" -ge 2 ]";
  r = run("bash -c " +
          q(env + " RANK=1 " + train + " > /dev/null 2>&1 & P=$!; " + env + " RANK=0 " + train +
            " & Q=$!; while kill -0 $Q 2>/dev/null && ! " + first_step + "; do sleep 0.1; done; kill -9 $P; wait $Q"));
  INFO(r.output);
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("lost contact with the others"));
}

TEST_CASE("a full disk: exit 2 naming the file, no temp files left, no broken file under a final name",
          "[cli][errors][disk][solo]") {
  test::Scratch s("full_disk");
  const auto disk = s.dir / "disk";
  std::filesystem::create_directories(disk);
  if (test::run_shell("mount -t tmpfs -o size=200k tmpfs " + q(disk)).code != 0)
    SKIP_TEST("cannot mount a tmpfs here (needs root)");
  struct Unmount {
    std::filesystem::path dir;
    ~Unmount() { test::run_shell("umount " + test::q(dir)); }
  } unmount{disk};
  const auto model = test::source_dir() / "models" / "flatnet-sim-transpose.flatnet";
  for (const std::string& what : std::vector<std::string>{"", " --state-dict"}) {
    INFO(what);
    const auto r = test::run_flatnet("export --model " + q(model) + what + " --out " + q(disk / "m.out"));
    CHECK(r.code == 2);
    CHECK_THAT(r.output, Contains("m.out") && Contains("write failed"));
    CHECK(std::filesystem::is_empty(disk));  // neither the final name nor a temporary file
  }
  // Reconstructions until the disk fills: an error, and every file left is a whole image.
  const auto r = test::run_flatnet("recon --method tikhonov --batch 1 --input " +
                                   q(test::data_dir() / "golden" / "*_raw.png") + " --out " + q(disk / "rec"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("write failed"));
  for (const auto& e : std::filesystem::directory_iterator(disk / "rec")) {
    INFO(e.path());
    if (e.path().filename() == kOutputMarker || e.path().filename() == kOutputLock) continue;  // the folder's claim
    CHECK(e.path().filename().string()[0] != '.');
    CHECK(read_rgb(e.path()).size(0) == 3);
  }
}

TEST_CASE("flatnet report: the table, the figure, timings, and it resumes from what is on disk", "[cli][report]") {
  test::Scratch s("report");
  for (const char* stem : {"bsds_16052", "inet_n02980441_castle"}) {
    std::filesystem::create_directories(s.dir / "set" / "meas");
    std::filesystem::create_directories(s.dir / "set" / "gt");
    std::filesystem::copy_file(test::data_dir() / "golden" / (std::string(stem) + "_raw.png"),
                               s.dir / "set" / "meas" / (std::string(stem) + ".png"));
    std::filesystem::copy_file(test::data_dir() / "golden" / (std::string(stem) + "_scene.png"),
                               s.dir / "set" / "gt" / (std::string(stem) + ".png"));
  }
  const auto model = test::source_dir() / "models" / "flatnet-sim-transpose.flatnet";
  const std::string cmd = "report --sets display=" + q(s.dir / "set") + " --methods tikhonov,tv,transpose=" + q(model) +
                          " --tv-count 1 --precision fp32 --out " + q(s.dir / "out");
  auto r = test::run_flatnet(cmd);
  INFO(r.output);
  REQUIRE(r.code == 0);
  const auto md = read_lines(s.dir / "out" / "report.md");
  std::string text;
  for (const auto& l : md) text += l + "\n";
  CHECK_THAT(text, Contains("| method | images | PSNR dB | SSIM | NIQE | ms per image |"));
  CHECK_THAT(text, Contains("| tikhonov | 2 |") && Contains("| tv | 1 |") && Contains("| transpose | 2 |") &&
                       Contains("| ground truth | 2 | - | - |"));
  CHECK(std::filesystem::exists(s.dir / "out" / "display_figure.png"));
  {
    std::ifstream html_file(s.dir / "out" / "report.html");
    const std::string html((std::istreambuf_iterator<char>(html_file)), {});
    CHECK_THAT(html, Contains("data-method=\"transpose\"") && Contains("data-method=\"tikhonov\"") &&
                         Contains("<td>bsds_16052.png</td>"));
  }
  CHECK(read_rgb(s.dir / "out" / "display" / "transpose" / "bsds_16052.png").size(1) == 256);
  // Resumed: nothing is made again, and one missing reconstruction is made alone.
  r = test::run_flatnet(cmd);
  CHECK(r.code == 0);
  CHECK(r.output.find("to make") == std::string::npos);
  std::filesystem::remove(s.dir / "out" / "display" / "tikhonov" / "bsds_16052.png");
  r = test::run_flatnet(cmd);
  CHECK_THAT(r.output, Contains("tikhonov: 1 of 2 to make"));
  // Another model under the same method name: its own reconstructions, never the old model's.
  const auto before = read_rgb(s.dir / "out" / "display" / "transpose" / "bsds_16052.png");
  const auto calibfree = test::source_dir() / "models" / "flatnet-sim-calibfree.flatnet";
  std::string other_cmd = cmd;
  other_cmd.replace(other_cmd.find(q(model)), q(model).size(), q(calibfree));
  r = test::run_flatnet(other_cmd);
  INFO(r.output);
  CHECK(r.code == 0);
  CHECK_THAT(r.output, Contains("transpose: the reconstructions on disk were made by another model") &&
                           Contains("transpose: 2 of 2 to make"));
  CHECK_FALSE(torch::equal(read_rgb(s.dir / "out" / "display" / "transpose" / "bsds_16052.png"), before));
  // A set without ground truth, or a method that is not one, is named.
  r = test::run_flatnet("report --sets " + q(s.dir / "set" / "meas") + " --out " + q(s.dir / "o2"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("not an evaluation set"));
  r = test::run_flatnet("report --sets " + q(s.dir / "set") + " --methods wiener --out " + q(s.dir / "o2"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("'wiener': expected tikhonov, tv or NAME=MODEL.flatnet"));
}

TEST_CASE("mask camera: a camera from codes works downstream (simulate, recon), and bad codes are named",
          "[cli][separable]") {
  test::Scratch s("codes_camera");
  const auto mls_codes = test::source_dir() / "models" / "camera" / "codes_mls.mat";
  auto r = test::run_flatnet("mask camera --codes " + q(mls_codes) + " --out " + q(s.dir / "mls"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("mean transmittance 0.5"));
  // With the MLS codes it is the reference camera: the same noise-free golden capture.
  const auto rig = load_rig(s.dir / "mls" / "rig.mat"), shipped = load_rig(test::rig_path());
  CHECK((rig.phil - shipped.phil).abs().max().item<double>() < 1e-6);
  auto photos = make_photos(s.dir / "photos");
  r = test::run_flatnet("simulate --camera " + q(s.dir / "mls" / "camera.yaml") + " --images " + q(photos) + " --out " +
                        q(s.dir / "ds") + " --noise off --val-fraction 0.5");
  INFO(r.output);
  REQUIRE(r.code == 0);
  const auto mine = read_gray16(s.dir / "ds" / "meas" / "bsds_16052_scene.png");
  const auto golden = read_gray16(test::data_dir() / "golden" / "bsds_16052_raw.png");
  CHECK((mine - golden).abs().max().item<int>() <= 64);  // within one ADC code
  r = test::run_flatnet("recon --camera " + q(s.dir / "mls" / "camera.yaml") + " --input " + q(s.dir / "ds" / "meas") +
                        " --out " + q(s.dir / "rec"));
  CHECK(r.code == 0);
  // Existing camera files are kept unless --force; codes out of range are refused by name.
  r = test::run_flatnet("mask camera --codes " + q(mls_codes) + " --out " + q(s.dir / "mls"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("already exists"));
  write_mat(s.dir / "bad.mat", {{"code_rows", torch::full({511, 1}, 2.0, torch::kFloat64)},
                                {"code_cols", torch::ones({511, 1}, torch::kFloat64)}});
  r = test::run_flatnet("mask camera --codes " + q(s.dir / "bad.mat") + " --out " + q(s.dir / "bad"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("bad.mat") && Contains("code_rows") && Contains("[-1, 1]"));
}

TEST_CASE("cmake --install gives a binary that finds its files from any folder, without the source tree",
          "[cli][install]") {
  test::Scratch s("install");
  const auto prefix = s.dir / "prefix";
  auto r = test::run_shell("cmake --install " + q(FLATNET_BUILD_DIR) + " --prefix " + q(prefix));
  INFO(r.output);
  REQUIRE(r.code == 0);
  const auto bin = prefix / "bin" / "flatnet";
  const auto share = prefix / "share" / "flatnet";
  REQUIRE(std::filesystem::exists(bin));
  CHECK(std::filesystem::exists(share / "configs" / "defaults.yaml"));
  CHECK(std::filesystem::exists(share / "configs" / "cameras" / "sim.yaml"));
  CHECK(std::filesystem::exists(share / "models" / "camera" / "calib.mat"));
  CHECK(std::filesystem::exists(share / "models" / "flatnet-sim-transpose.flatnet"));
  // From another folder, FLATNET_DATA_DIR unset: the default camera (configs/cameras/sim.yaml, whose
  // calibration is ../../models/camera/calib.mat) comes from the installed share folder.
  std::filesystem::create_directories(s.dir / "elsewhere");
  const auto capture = test::data_dir() / "golden" / "bsds_16052_raw.png";
  r = test::run_shell("cd " + q(s.dir / "elsewhere") + " && env -u FLATNET_DATA_DIR " + q(bin) + " recon --input " +
                      q(capture) + " --out rec");
  INFO(r.output);
  CHECK(r.code == 0);
  CHECK(std::filesystem::exists(s.dir / "elsewhere" / "rec" / "bsds_16052_raw.png"));
  r = test::run_shell("cd " + q(s.dir / "elsewhere") + " && env -u FLATNET_DATA_DIR " + q(bin) + " infer --model " +
                      q(share / "models" / "flatnet-sim-transpose.flatnet") + " --input " + q(capture) + " --out inf");
  INFO(r.output);
  CHECK(r.code == 0);
  // A copy of the binary with no share folder next to it says where it looked and what to set.
  std::filesystem::create_directories(s.dir / "lonely" / "bin");
  std::filesystem::copy_file(bin, s.dir / "lonely" / "bin" / "flatnet");
  r = test::run_shell("env -u FLATNET_DATA_DIR " + q(s.dir / "lonely" / "bin" / "flatnet") + " recon --input " +
                      q(capture) + " --out " + q(s.dir / "lonely" / "rec"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("FLATNET_DATA_DIR"));
  r = test::run_shell("FLATNET_DATA_DIR=" + q(share) + " " + q(s.dir / "lonely" / "bin" / "flatnet") +
                      " recon --input " + q(capture) + " --out " + q(s.dir / "lonely" / "rec"));
  INFO(r.output);
  CHECK(r.code == 0);
}

TEST_CASE("flatnet bench: rows, JSON, and --profile lists the operators of one more run", "[cli][bench]") {
  test::Scratch s("bench");
  const auto json_path = s.dir / "bench.json";
  const auto r = test::run_flatnet(
      "bench --rows tikhonov,infer_cpu --precision fp32 --repeats 1 --warmup 0 --profile 5 "
      "--json " +
      q(json_path));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("tikhonov") && Contains("infer_cpu") && Contains("profile of one more run"));
  CHECK_THAT(r.output, Contains("flatnet::onednn_bmm"));  // Tikhonov is batched GEMMs, in oneDNN
  CHECK_THAT(r.output, Contains("aten::"));
  const auto bytes = read_bytes(json_path);
  const auto j = nlohmann::json::parse(std::string(bytes.begin(), bytes.end()));
  REQUIRE(j["rows"].size() == 2);
  for (const auto& row : j["rows"]) {
    INFO(row["name"]);
    CHECK(row["median_ms"].get<double>() > 0);
    REQUIRE(row.contains("profile"));
    REQUIRE(!row["profile"].empty());
    double previous = 1e300;
    for (const auto& op : row["profile"]) {  // by self time, largest first; self never exceeds total
      CHECK(op["calls"].get<int64_t>() > 0);
      CHECK(op["self_ms"].get<double>() <= op["total_ms"].get<double>() + 1e-9);
      CHECK(op["self_ms"].get<double>() <= previous);
      previous = op["self_ms"].get<double>();
    }
  }
  const auto bad = test::run_flatnet("bench --rows tikhonov --repeats 1 --profile -1");
  CHECK(bad.code == 2);
  CHECK_THAT(bad.output, Contains("--profile"));
  const auto unknown = test::run_flatnet("bench --rows warp_drive --repeats 1");
  CHECK(unknown.code == 2);
  CHECK_THAT(unknown.output, Contains("warp_drive") && Contains("tikhonov"));
}

TEST_CASE("FLOP counting: convolutions, transposed convolutions and GEMMs exactly, 2 per multiply-add",
          "[bench][flops]") {
  c10::InferenceMode guard;
  const auto x = torch::randn({2, 3, 10, 12}), w = torch::randn({5, 3, 3, 3});
  // As nn::Conv2d calls it (every size given per axis: LibTorch's counter needs that).
  const std::vector<int64_t> one{1, 1};
  // 'same' 3x3: every output pixel of 5 channels takes 3x3x3 multiply-adds.
  CHECK(count_gflop([&] { torch::conv2d(x, w, torch::Tensor(), one, one, one); }) * 1e9 ==
        Approx(2.0 * 2 * 5 * 10 * 12 * 3 * 9));
  // stride 2, no padding: outputs 4x5.
  CHECK(count_gflop([&] {
          const std::vector<int64_t> stride{2, 2}, pad{0, 0};
          torch::conv2d(x, w, torch::Tensor(), stride, pad, one);
        }) * 1e9 ==
        Approx(2.0 * 2 * 5 * 4 * 5 * 3 * 9));
  // 2x2 stride-2 transposed: every input pixel scatters to 2x2 outputs of 7 channels.
  const auto wt = torch::randn({3, 7, 2, 2});
  CHECK(count_gflop([&] { torch::conv_transpose2d(x, wt, {}, 2); }) * 1e9 == Approx(2.0 * 2 * 3 * 10 * 12 * 7 * 4));
  const auto a = torch::randn({30, 40}), b = torch::randn({40, 50});
  CHECK(count_gflop([&] { torch::mm(a, b); }) * 1e9 == Approx(2.0 * 30 * 40 * 50));
}

TEST_CASE("FLOP counting of a training step: the backward's two gradients, each the forward's work", "[bench][flops]") {
  const auto x = torch::randn({2, 3, 10, 12}, torch::requires_grad());
  const auto w = torch::randn({5, 3, 3, 3}, torch::requires_grad());
  const std::vector<int64_t> one{1, 1};
  const double forward = 2.0 * 2 * 5 * 10 * 12 * 3 * 9;
  const double counted =
      count_gflop([&] { torch::conv2d(x, w, torch::Tensor(), one, one, one).sum().backward(); }) * 1e9;
  // forward + 2 x forward, and the sum's and its backward's few elementwise operations
  CHECK(counted >= 3 * forward);
  CHECK(counted < 3 * forward + 4 * 2 * 5 * 10 * 12);
}

TEST_CASE("FLOP counting under autocast counts a convolution once, flatnet's own oneDNN convolution by its passes",
          "[bench][flops]") {
  const auto x = torch::randn({2, 3, 10, 12}), w = torch::randn({5, 3, 3, 3});
  const std::vector<int64_t> one{1, 1};
  const double forward = 2.0 * 2 * 5 * 10 * 12 * 3 * 9;
  if (resolve_precision("auto") == Precision::bf16) {  // LibTorch's bf16 convolutions need AVX-512
    AutocastGuard autocast(true);  // LibTorch's autocast kernel casts, then calls aten::conv2d again
    c10::InferenceMode guard;
    CHECK(count_gflop([&] { torch::conv2d(x, w, torch::Tensor(), one, one, one); }) * 1e9 == Approx(forward));
  }
  const auto xl = x.contiguous(at::MemoryFormat::ChannelsLast);
  const auto wl = w.clone().requires_grad_();
  const double counted = count_gflop([&] { onednn_conv2d(xl, wl, {}, 1, 1).sum().backward(); }) * 1e9;
  CHECK(counted >= 2 * forward);  // the forward and the weight's gradient (x wants none)
  CHECK(counted < 2 * forward + 4 * 2 * 5 * 10 * 12);
}

TEST_CASE("flatnet bench --rows peak: the practical peak first, then each row's GFLOP/s and share of it",
          "[cli][bench][flops]") {
  test::Scratch s("bench_peak");
  const auto json_path = s.dir / "bench.json";
  // Asked after the row it calibrates, the peak still runs first.
  const auto r =
      test::run_flatnet("bench --rows tikhonov,peak --precision fp32 --repeats 1 --warmup 0 --json " + q(json_path));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("GFLOP/s") && Contains("peak %") && Contains("peak_gemm_fp32"));
  const auto bytes = read_bytes(json_path);
  const auto j = nlohmann::json::parse(std::string(bytes.begin(), bytes.end()));
  REQUIRE(j["rows"].size() >= 3);
  CHECK(j["rows"][0]["name"] == "peak_gemm_fp32");
  const auto& tik = j["rows"].back();
  REQUIRE(tik["name"] == "tikhonov");
  CHECK(tik["gflop"].get<double>() > 0.1);  // batched GEMMs of 500x620 planes
  CHECK(tik["gflops"].get<double>() > 0);
  // The share is the row's rate over its precision's peak, the faster of the two peak rows (a
  // relation between the printed numbers; the numbers themselves are timings and go unchecked).
  double peak = 0;
  for (const auto& row : j["rows"]) {
    const auto name = row["name"].get<std::string>();
    if (name.rfind("peak_", 0) == 0 && name.size() > 4 && name.substr(name.size() - 4) == "fp32")
      peak = std::max(peak, row["gflops"].get<double>());
  }
  REQUIRE(peak > 0);
  CHECK(tik["peak_share"].get<double>() == Approx(tik["gflops"].get<double>() / peak).epsilon(1e-3));
  CHECK(j["rows"][0]["peak_share"].is_null());  // a peak row is not a share of itself
}

TEST_CASE("report inversion: the thesis's Figure 3.3 from the shipped models, and a model without an inversion refused",
          "[cli][inversion]") {
  test::Scratch s("cli_inversion");
  const auto models = test::source_dir() / "models";
  auto r = test::run_flatnet("report inversion --models T=" + q(models / "flatnet-sim-transpose.flatnet") + " --out " +
                             q(s.dir / "inv") + " --threads 1");
  REQUIRE(r.code == 0);
  CHECK(std::filesystem::exists(s.dir / "inv" / "inversion.png"));
  const auto md = read_file_text(s.dir / "inv" / "inversion.md", 1 << 20);
  CHECK(md.find("| T | transpose | W1^T PhiL |") != std::string::npos);
  auto missing = test::run_flatnet("report inversion --out " + q(s.dir / "inv2"));
  CHECK(missing.code == 2);
  CHECK(missing.output.find("--models") != std::string::npos);
}

TEST_CASE("flatnet options: every setting with its default, range and documentation", "[cli][config]") {
  auto r = test::run_flatnet("options train.batch");
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("train.batch") && Contains("scenes per step") && Contains("[1 to 4096 samples]"));
  r = test::run_flatnet("options --for mask mask. --markdown");
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("| `mask.rank` | `1` | 1 to 511 |"));
  CHECK_THAT(r.output, Contains("sigmoid \\| clamp"));  // a '|' in the text does not end the cell
  CHECK_FALSE(Contains("train.").match(r.output));
  r = test::run_flatnet("options nosuch.");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("defaults.yaml") && Contains("no setting starting with 'nosuch.'"));
  // A camera file's keys: each with its one range, the bench's too.
  r = test::run_flatnet("options --for camera");
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("noise_gain") && Contains("[0, 1) full scale") && Contains("display_gamma") &&
                           Contains("0 (the sRGB curve) or a power within [0.5, 3]") && Contains("bench.crosstalk") &&
                           Contains("hot_pixels") && Contains("colour_mix"));
  r = test::run_flatnet("options --for gan");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("give train, mask, separable, camera, simulate"));
}

TEST_CASE("model cards: flatnet info tells what a model file holds, export records held-out scores",
          "[cli][info][slow]") {
  test::Scratch s("info");
  auto photos = make_photos(s.dir / "photos");
  REQUIRE(
      test::run_flatnet("simulate --images " + q(photos) + " --out " + q(s.dir / "ds") + " --val-fraction 0.5").code ==
      0);
  auto r = test::run_flatnet("train --config " + q(test::source_dir() / "configs" / "sim_transpose.yaml") +
                             " --set data.dataset=" + q(s.dir / "ds") + " --set model.unet.width=2" + kOnDisk +
                             " --set loss.stripe=3 --set train.iterations=3 --set train.val_every=1 --out " +
                             q(s.dir / "run"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  const auto model = s.dir / "run" / "model.flatnet";

  // The file's SHA-256 is the one sha256sum computes; training is recorded.
  const auto sum = test::run_shell("sha256sum " + q(model));
  REQUIRE(sum.code == 0);
  const auto hash = sum.output.substr(0, 64);
  r = test::run_flatnet("info " + q(model));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("sha256    " + hash));
  CHECK_THAT(r.output, Contains("model file") && Contains("U-Net, width 2") && Contains("transpose init"));
  CHECK_THAT(r.output, Contains("3 steps") && Contains("best validation PSNR"));
  CHECK_THAT(r.output, Contains("written   20") && Contains("none recorded"));
  CHECK_THAT(r.output, Contains("1 mse + 0.2 ssim") && Contains(" + 3 stripe"));  // every term of the loss

  // A checkpoint too, shown with its moving average when it kept one.
  r = test::run_flatnet("info " + q(s.dir / "run" / "latest.ckpt"));
  CHECK(r.code == 0);
  CHECK_THAT(r.output, Contains("training checkpoint") && Contains("3 steps"));

  // Scores from `flatnet eval` into a copy of the model; the weights do not change.
  REQUIRE(test::run_flatnet("infer --model " + q(model) + " --input " + q(s.dir / "ds" / "meas") + " --out " +
                            q(s.dir / "eval" / "tiny"))
              .code == 0);
  r = test::run_flatnet("eval --niqe none --gt " + q(s.dir / "ds" / "gt") + " --out " + q(s.dir / "eval"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  REQUIRE(std::filesystem::exists(s.dir / "eval" / "scores.json"));
  const auto scored = s.dir / "scored.flatnet";
  r = test::run_flatnet("export --model " + q(model) + " --out " + q(scored) +
                        " --scores heldout=" + q(s.dir / "eval"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  r = test::run_flatnet("info --json " + q(scored));
  REQUIRE(r.code == 0);
  const auto j = nlohmann::json::parse(r.output);
  CHECK(j["kind"] == "model");
  CHECK(j["trained_steps"] == "3");
  CHECK(j["scores"]["heldout"]["method"] == "tiny");
  CHECK(j["scores"]["heldout"]["images"] == 2);
  CHECK(j["scores"]["heldout"]["psnr"].get<double>() > 0);
  CHECK(j["scores"]["heldout"]["niqe"].is_null());
  CHECK(j["parameters"].get<int64_t>() > 0);
  CHECK_THAT(j["model_spec"].get<std::string>(), Contains("width: 2"));
  CHECK_THAT(j["config"].get<std::string>(), Contains("train:"));
  r = test::run_flatnet("info " + q(scored));
  CHECK_THAT(r.output, Contains("heldout") && Contains("(2 images)"));
  CHECK_THAT(r.output, !Contains("\\x0a"));  // the scores' own line breaks are not escaped
  // Same weights as the file it was made from.
  auto a = load_model_file(model), b = load_model_file(scored);
  for (const auto& p : a.generator->named_parameters())
    CHECK(torch::equal(p.value(), b.generator->named_parameters()[p.key()]));

  // The capture's data-consistency step set at export as the file's default at inference: the same
  // weights, its provenance says it was not trained with, infer applies it unless told otherwise.
  const auto stepped = s.dir / "stepped.flatnet";
  r = test::run_flatnet("export --model " + q(model) + " --data-consistency 3 --consistency-blur 2 --out " +
                        q(stepped));
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("applies data consistency c 3, blur 2 at inference"));
  r = test::run_flatnet("info " + q(stepped));
  CHECK_THAT(r.output, Contains("(data consistency c 3, blur 2 px)") && Contains("set at export, not trained with"));
  CHECK(load_model_file(stepped).spec.consistency_strength == 3);
  const auto infer_into = [&](const std::string& model_file, const std::string& name, const std::string& flags) {
    const auto run = test::run_flatnet("infer --model " + q(model_file) + " --input " + q(s.dir / "ds" / "meas") +
                                       " --out " + q(s.dir / name) + flags);
    INFO(run.output);
    REQUIRE(run.code == 0);
    std::vector<std::filesystem::path> pictures;
    for (const auto& e : std::filesystem::directory_iterator(s.dir / name))
      if (e.path().extension() == ".png") pictures.push_back(e.path());
    REQUIRE(!pictures.empty());
    std::sort(pictures.begin(), pictures.end());
    return read_rgb(pictures.front());
  };
  const auto by_default = infer_into(stepped.string(), "dc_default", "");
  CHECK(torch::equal(by_default, infer_into(model.string(), "dc_given", " --data-consistency 3 --consistency-blur 2")));
  CHECK_FALSE(torch::equal(by_default, infer_into(stepped.string(), "dc_off", " --data-consistency off")));
  r = test::run_flatnet("export --model " + q(stepped) + " --data-consistency off --out " + q(s.dir / "plain.flatnet"));
  CHECK(r.code == 0);
  CHECK(load_model_file(s.dir / "plain.flatnet").spec.consistency_strength == 0);
  r = test::run_flatnet("export --model " + q(model) + " --consistency-blur 1 --out " + q(s.dir / "x.flatnet"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("needs --data-consistency"));
  r = test::run_flatnet("export --model " + q(model) + " --data-consistency 3 --state-dict --out " + q(s.dir / "x.pt"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("not in ONNX or state-dict"));
  r = test::run_flatnet("export --model " + q(model) + " --data-consistency nan --out " + q(s.dir / "x.flatnet"));
  CHECK(r.code == 2);
  CHECK_FALSE(std::filesystem::exists(s.dir / "x.flatnet"));

  // The mean of a model file and a checkpoint (its moving average), recorded as such; one input
  // kind at a time, and never over one of the inputs.
  r = test::run_flatnet("export --average-of " + q(model) + "," + q(s.dir / "run" / "latest.ckpt") + " --out " +
                        q(s.dir / "mean.flatnet"));
  INFO(r.output);
  REQUIRE(r.code == 0);
  r = test::run_flatnet("info " + q(s.dir / "mean.flatnet"));
  CHECK_THAT(r.output, Contains("mean of 2 models: model.flatnet, latest.ckpt") && Contains("3 steps"));
  r = test::run_flatnet("export --average-of " + q(model) + "," + q(scored) + " --model " + q(model) + " --out " +
                        q(s.dir / "x.flatnet"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--average-of"));
  r = test::run_flatnet("export --average-of " + q(model) + "," + q(scored) + " --force --out " + q(scored));
  CHECK(r.code == 2);
  CHECK(load_model_file(scored).provenance.scores.size() > 0);  // the input is untouched

  // Bad input: a scores file that is not one, a method that is not there, a file that is not a model.
  std::ofstream(s.dir / "junk.json") << "{not json";
  r = test::run_flatnet("export --model " + q(model) + " --out " + q(s.dir / "x.flatnet") +
                        " --scores a=" + q(s.dir / "junk.json"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("junk.json") && Contains("scores.json"));
  r = test::run_flatnet("export --model " + q(model) + " --out " + q(s.dir / "x.flatnet") +
                        " --method other --scores a=" + q(s.dir / "eval"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("no method 'other'") && Contains("tiny"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "x.flatnet"));
  r = test::run_flatnet("info " + q(s.dir / "junk.json"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("junk.json"));
}
