// Hostile inputs, third round (issue 40): names that would become paths, lock files that are links,
// files that lie about their sizes, YAML that expands without bound, checkpoints whose state breaks
// its own rules, and strings that would drive the terminal. Each case failed before its fix.
#include "catch_torch.hpp"

#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <csignal>
#include <fstream>

#include <onnx/onnx_pb.h>

#include "core/error.hpp"
#include "core/output_dir.hpp"
#include "core/util.hpp"
#include "eval/thesis_report.hpp"
#include "helpers.hpp"
#include "io/camera_config.hpp"
#include "io/config.hpp"
#include "io/image.hpp"
#include "io/torch_file.hpp"
#include "io/yaml_text.hpp"
#include "nn/onnx_export.hpp"
#include "nn/optimizer_state.hpp"
#include "optics/camera.hpp"
#include "optics/simulator.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;
using test::q;
using test::read_file;
using test::write_file;

TEST_CASE("a name from a flag or a file becomes one path component or is refused", "[safe][hostile]") {
  for (const std::string good : {"tikhonov", "flatnet-transpose", "lab v2", "dim_room.2"})
    CHECK_NOTHROW(require_plain_name(good, "report.sets"));
  for (const std::string& bad : std::vector<std::string>{"", "..", ".", "../x", "/tmp/x", "a/b", "a\\b", ".hidden",
                                                         "a\x1b[2Jb", std::string(200, 'a')})
    CHECK_THROWS_WITH(require_plain_name(bad, "report.methods"), Contains("report.methods"));
  CHECK_THROWS_WITH(parse_report_set("../other=/tmp"), Contains("report.sets") && Contains("separator"));
}

TEST_CASE("flatnet report: method and set names never leave --out, and folders it did not write are never emptied",
          "[safe][hostile][cli]") {
  test::Scratch s("hostile_report");
  const auto victim = s.dir / "victim";
  std::filesystem::create_directories(victim);
  write_file(victim / "precious.txt", "keep me");
  const auto set = s.dir / "set";
  std::filesystem::create_directories(set / "gt");
  std::filesystem::create_directories(set / "meas");
  std::filesystem::copy_file(test::data_dir() / "golden" / "bsds_16052_raw.png", set / "meas" / "a.png");
  std::filesystem::copy_file(test::data_dir() / "golden" / "bsds_16052_scene.png", set / "gt" / "a.png");
  const auto model = test::source_dir() / "models" / "flatnet-sim-transpose.flatnet";
  for (const auto& spec : {"--methods " + q(victim) + "=" + q(model) + " --sets " + q(set),
                           "--methods tikhonov --sets " + q("../victim=" + set.string()),
                           "--methods " + q("../victim=" + model.string()) + " --sets " + q(set)}) {
    INFO(spec);
    const auto r = test::run_flatnet("report " + spec + " --out " + q(s.dir / "out"));
    CHECK(r.code == 2);
    CHECK_THAT(r.output, Contains("a name becomes one file or folder name"));
  }
  CHECK(read_file(victim / "precious.txt") == "keep me");
  // A folder inside --out that flatnet report did not make (no method.txt) is not emptied.
  ReportOptions o;
  o.out = s.dir / "out2";
  o.methods = {{"tikhonov", "tikhonov", {}}};
  o.sets = {{"set", set}};
  o.camera = load_camera_config(test::source_dir() / "configs" / "cameras" / "sim.yaml");
  o.progress = false;
  std::filesystem::create_directories(o.out / "set" / "tikhonov");
  write_file(o.out / "set" / "tikhonov" / "mine.png", "not flatnet's");
  CHECK_THROWS_WITH(make_report(o), Contains("did not write"));
  CHECK(read_file(o.out / "set" / "tikhonov" / "mine.png") == "not flatnet's");
}

TEST_CASE("an output folder's lock is never followed through a link", "[safe][hostile]") {
  test::Scratch s("hostile_lock");
  const auto victim = s.dir / "victim.txt";
  write_file(victim, "the user's file");
  const auto out = s.dir / "out";
  std::filesystem::create_directories(out);
  std::filesystem::create_symlink(victim, out / kOutputLock);
  OutputRole role;
  role.command = "recon";
  CHECK_THROWS_WITH(claim_output_folder(out, role), Contains(kOutputLock) && Contains("symbolic link"));
  role.force = true;
  CHECK_THROWS_WITH(claim_output_folder(out, role), Contains("symbolic link"));
  CHECK(read_file(victim) == "the user's file");
}

TEST_CASE("ONNX tensors are checked against their bytes before any engine reads them", "[safe][hostile][onnx]") {
  test::Scratch s("hostile_onnx");
  auto graph_with = [&](const std::vector<int64_t>& dims, size_t bytes) {
    onnx::ModelProto m;
    m.set_ir_version(8);
    auto* g = m.mutable_graph();
    auto* t = g->add_initializer();
    t->set_name("w");
    t->set_data_type(onnx::TensorProto::FLOAT);
    for (auto d : dims) t->add_dims(d);
    t->set_raw_data(std::string(bytes, '\0'));
    auto add_io = [](onnx::ValueInfoProto* v, const char* name, std::vector<int64_t> shape) {
      v->set_name(name);
      auto* tt = v->mutable_type()->mutable_tensor_type();
      tt->set_elem_type(onnx::TensorProto::FLOAT);
      for (auto d : shape) tt->mutable_shape()->add_dim()->set_dim_value(d);
    };
    add_io(g->add_input(), "meas", {1, 4, 20, 24});
    add_io(g->add_output(), "image", {1, 3, 16, 16});
    std::string out;
    m.SerializeToString(&out);
    const auto path = s.dir / ("m" + std::to_string(bytes) + ".onnx");
    write_file(path, out);
    return path;
  };
  CHECK_THROWS_WITH(read_onnx_info(graph_with({256, 1024, 1024}, 4)),
                    Contains("ONNX tensor 'w'") && Contains("holds 4 bytes"));
  CHECK_THROWS_WITH(read_onnx_info(graph_with({1, 3, 256, 256}, 4)), Contains("holds 4 bytes"));
  CHECK_THROWS_WITH(read_onnx_info(graph_with({-1, 4}, 16)), Contains("impossible shape"));
  CHECK_NOTHROW(read_onnx_info(graph_with({2, 3}, 24)));  // an honest tensor passes
  // The CLI refuses it in one line, before OpenCV DNN sees the file.
  const auto r = test::run_flatnet("infer --engine opencv --model " + q(graph_with({256, 1024, 1024}, 4)) +
                                   " --input " + q(s.dir / "none.png") + " --out " + q(s.dir / "out"));
  CHECK(r.code == 2);
}

TEST_CASE("YAML: an alias bomb is refused at once, in every reader", "[safe][hostile][yaml]") {
  // Nine levels of nine aliases each: 9^9 = 387 M nodes from ~600 bytes.
  std::string bomb = "a: &a [x, x, x, x, x, x, x, x, x]\n";
  for (char c = 'b'; c <= 'i'; ++c) {
    const std::string prev(1, static_cast<char>(c - 1));
    bomb += std::string(1, c) + ": &" + c + " [*" + prev + ", *" + prev + ", *" + prev + ", *" + prev + ", *" + prev +
            ", *" + prev + ", *" + prev + ", *" + prev + ", *" + prev + "]\n";
  }
  // The message is the refusal's own (the expansion is counted, not carried out); no clock judges it,
  // so a loaded machine cannot fail it.
  CHECK_THROWS_WITH(parse_yaml_document(bomb, "bomb.yaml"), Contains("bomb.yaml") && Contains("expands to more than"));
  CHECK_THROWS_WITH(camera_from_yaml_text(bomb, "camera.yaml"), Contains("expands to more than"));
  test::Scratch s("hostile_yaml");
  write_file(s.dir / "bomb.yaml", bomb);
  const auto r = test::run_flatnet("train --config " + q(s.dir / "bomb.yaml") + " --out " + q(s.dir / "run"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("expands to more than"));
}

TEST_CASE("names flatnet writes into YAML read back as the same names", "[safe][hostile][yaml]") {
  for (const std::string name : {"FlatCam: lab v2", "#1", "- x", "\"quoted\"", "a 'b' c", "yes", "~", "[1, 2]",
                                 "{a: b}", "line\nbreak", "&anchor", "*alias", "tab\there", "!tag"}) {
    INFO(name);
    CameraConfig c;
    c.name = name;
    const auto back = camera_from_yaml_text(camera_geometry_yaml(c), "camera");
    CHECK(back.name == name);
  }
}

TEST_CASE("a dataset's settings record reads back as written, whatever its folder is called",
          "[safe][hostile][yaml][optics]") {
  test::Scratch s("simrecord");
  const auto rig = load_rig(test::rig_path());
  SimulateOptions o;
  o.images = test::make_photos(s.dir / "photos: a #b\nc - d");
  o.out = s.dir / "out";
  o.limit = 1, o.workers = 1;
  simulate_dataset(rig, o);
  const auto record = parse_yaml_document(read_file(o.out / "simulate.yaml"), "simulate.yaml");
  CHECK(record["images"].Scalar() == std::filesystem::weakly_canonical(o.images).string());
  CHECK(record["lamp_gain"].Scalar() == "-");
  CHECK_NOTHROW(simulate_dataset(rig, o));  // the same settings: a rerun, not "other settings"
  o.seed = 7;
  CHECK_THROWS_WITH(simulate_dataset(rig, o), Contains("other settings") && Contains("seed 0 -> 7"));
  // A record written before values were quoted ("lamp_gain: -" reads as a YAML list) still matches.
  o.seed = 0;
  o.images = test::make_photos(s.dir / "plain");
  o.out = s.dir / "out_before_quoting";
  simulate_dataset(rig, o);
  std::string unquoted;
  for (const auto& kv : parse_yaml_document(read_file(o.out / "simulate.yaml"), "simulate.yaml"))
    unquoted += kv.first.Scalar() + ": " + kv.second.Scalar() + "\n";
  CHECK_THAT(unquoted, Contains("lamp_gain: -\n"));
  write_file(o.out / "simulate.yaml", unquoted);
  CHECK_NOTHROW(simulate_dataset(rig, o));
}

TEST_CASE("checkpoint state is checked by its own rules: Adam's moments and betas, step, the generator's state",
          "[safe][hostile][train]") {
  const auto ok = torch::ones({3}), negative = -torch::ones({3});
  CHECK_NOTHROW(require_adam_moments(5, ok, ok, "run/latest.ckpt", "optimizer.u."));
  CHECK_THROWS_WITH(require_adam_moments(5, ok, negative, "run/latest.ckpt", "optimizer.u."),
                    Contains("run/latest.ckpt") && Contains("exp_avg_sq") && Contains("negative"));
  CHECK_THROWS_WITH(require_adam_moments(-5, ok, ok, "run/latest.ckpt", "optimizer.u."), Contains("step"));
  CHECK_THROWS_WITH(require_adam_moments(1, ok * NAN, ok, "ck", "m."), Contains("NaN"));
  CHECK_NOTHROW(require_adam_options(0.9, 0.999, 1e-8, 1e-4, 0, "ck", "group 0"));
  CHECK_THROWS_WITH(require_adam_options(7.5, -3, 1e-8, 1e-4, 0, "ck", "group 0"), Contains("betas"));
  CHECK_THROWS_WITH(require_adam_options(0.9, 0.999, 0, 1e-4, 0, "ck", "group 0"), Contains("eps"));
  const auto state = at::detail::getDefaultCPUGenerator().get_state();
  CHECK_NOTHROW(require_cpu_generator_state(state, "ck", "rng_state"));
  CHECK_THROWS_WITH(require_cpu_generator_state(torch::full_like(state, 0xff), "run/latest.ckpt", "rng_state"),
                    Contains("run/latest.ckpt") && Contains("rng_state") && Contains("not a valid state"));
  CHECK_THROWS_WITH(require_cpu_generator_state(state.slice(0, 0, 10), "ck", "rng"), Contains("bytes expected"));
}

TEST_CASE("a torch.save archive whose version record claims a gigabyte is refused before LibTorch inflates it",
          "[safe][hostile][torchfile][solo]") {
  if (!test::python_has_torch() && std::system("/usr/bin/python3 -c 'import zipfile' >/dev/null 2>&1") != 0)
    SKIP_TEST("no /usr/bin/python3 to write the zip file");
  test::Scratch s("hostile_zip");
  const auto path = s.dir / "bomb.pt";
  // Python's zipfile, as another tool writes it: a tiny pickle, and a 64 MiB version record deflated.
  const auto r = test::run_shell(
      "/usr/bin/python3 -c \"import zipfile, sys; z = zipfile.ZipFile(sys.argv[1], 'w'); "
      "z.writestr('archive/data.pkl', b'\\x80\\x02}q\\x00.'); "
      "z.writestr('archive/version', b'3' * (64 << 20), compress_type=zipfile.ZIP_DEFLATED); z.close()\" " +
      q(path));
  REQUIRE(r.code == 0);
  CHECK(std::filesystem::file_size(path) < (1 << 20));
  CHECK_THROWS_WITH(read_torch_file(path), Contains("bomb.pt") && Contains("version record"));
}

TEST_CASE("strings from files are escaped before they reach a terminal", "[safe][hostile]") {
  CHECK(printable("plain text, ünïcode") == "plain text, ünïcode");
  CHECK(printable("\x1b]0;title\x07\x1b[2J") == "\\x1b]0;title\\x07\\x1b[2J");
  CHECK(printable("a\rb\nc\x7f") == "a\\x0db\\x0ac\\x7f");
  // The CLI's one-line errors escape what a file or flag held.
  test::Scratch s("hostile_tty");
  const auto r = test::run_flatnet("info " + q(s.dir / "\x1b[31mred.flatnet"));
  CHECK(r.code == 2);
  CHECK(r.output.find('\x1b') == std::string::npos);
  CHECK_THAT(r.output, Contains("\\x1b[31mred.flatnet"));
}

TEST_CASE("a setting that is not a config key is named as the user typed it", "[safe][hostile][cli]") {
  test::Scratch s("hostile_key");
  const auto r = test::run_flatnet("train --config " + q(test::source_dir() / "configs" / "sim_transpose.yaml") +
                                   " --set experiment.source_camera=X --out " + q(s.dir / "run"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("'experiment.source_camera'"));
  CHECK_THAT(r.output, !Contains("'--source-camera'"));
}

TEST_CASE("the training memory check counts the model's weights and optimiser state", "[safe][hostile][cli]") {
  test::Scratch s("hostile_width");
  const auto r = test::run_flatnet("train --config " + q(test::source_dir() / "configs" / "sim_transpose.yaml") +
                                   " --set model.unet.width=1024 --out " + q(s.dir / "run"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("model.unet.width") && Contains("optimiser state"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "run" / "latest.ckpt"));
}

TEST_CASE("SIGTERM outside a training step ends a command at once, and inside one the step finishes first",
          "[safe][hostile]") {
  // In a child process: the handler as the CLI installs it, then the signal.
  auto child = [](bool inside_step) {
    const pid_t pid = ::fork();
    if (pid == 0) {
      watch_interrupts();
      if (inside_step) {
        const FinishItemOnInterrupt step;
        std::raise(SIGTERM);
        ::_exit(interrupted() ? 42 : 1);  // the step went on, and the loop will see the flag
      }
      std::raise(SIGTERM);  // loading a config, say: nothing to finish
      ::_exit(0);           // not reached
    }
    int status = 0;
    ::waitpid(pid, &status, 0);
    return status;
  };
  const int outside = child(false);
  CHECK(WIFSIGNALED(outside));
  CHECK(WTERMSIG(outside) == SIGTERM);  // a shell reports 143
  const int inside = child(true);
  REQUIRE(WIFEXITED(inside));
  CHECK(WEXITSTATUS(inside) == 42);
}

TEST_CASE("a switch given a value is read by its value: --force=false never replaces, a bad value is refused",
          "[safe][hostile][cli]") {
  test::Scratch s("hostile_switch_value");
  const auto out = s.dir / "calib.mat";
  write_file(out, "the user's calibration");
  for (const std::string off : {"false", "0", "no", "OFF"}) {
    INFO(off);
    const auto r = test::run_flatnet("calibrate --rig " + q(test::rig_path()) + " --out " + q(out) + " --force=" + off);
    CHECK(r.code == 2);
    CHECK_THAT(r.output, Contains("exists"));
    CHECK(read_file(out) == "the user's calibration");
  }
  const auto bad = test::run_flatnet("calibrate --rig " + q(test::rig_path()) + " --out " + q(out) + " --force=maybe");
  CHECK(bad.code == 2);
  CHECK_THAT(bad.output, Contains("--force") && Contains("maybe") && Contains("true or false"));
  CHECK(read_file(out) == "the user's calibration");
}

TEST_CASE("a camera's rotation is radians: a value in degrees is refused with its unit named", "[safe][hostile]") {
  const std::string base =
      "name: r\nraw_height: 64\nraw_width: 64\nadc_bits: 10\ncrop: [0, 0, 32, 32]\nscene_size: 16\n";
  CHECK_NOTHROW(camera_from_yaml_text(base + "rotation: 0.00174\n", "cam.yaml"));
  CHECK_NOTHROW(camera_from_yaml_text(base + "rotation: -0.1\n", "cam.yaml"));
  for (const std::string bad : {"90", "400", "-3.1416", "1"}) {
    INFO(bad);
    CHECK_THROWS_WITH(camera_from_yaml_text(base + "rotation: " + bad + "\n", "cam.yaml"),
                      Contains("cam.yaml") && Contains("radians"));
  }
}

TEST_CASE("a string setting that looks like YAML is written back as the same string, and reads back",
          "[safe][hostile][config]") {
  test::Scratch s("hostile_config_string");
  for (const std::string value : {"[&a0 [x, y], *a0, *a0, *a0]", "[my photos", "[a, [b]]", "plain"}) {
    INFO(value);
    const auto c = Config::load({}, {"data.images=" + value});
    std::string yaml;
    REQUIRE_NOTHROW(yaml = c.to_yaml());
    write_file(s.dir / "config.yaml", yaml);
    const auto back = Config::load(s.dir / "config.yaml");
    CHECK(back.str("data.images") == value);
  }
}

TEST_CASE("a --set value is taken whole: a comma is part of the value and not a second setting",
          "[safe][hostile][cli]") {
  test::Scratch s("hostile_set_comma");
  const auto r = test::run_flatnet("train --config " + q(test::source_dir() / "configs" / "sim_transpose.yaml") +
                                   " --set train.minutes=1,5 --out " + q(s.dir / "run"));
  CHECK(r.code == 2);
  // The value reaches the setting as typed (before: split into 'train.minutes=1' and a bare '5').
  CHECK_THAT(r.output, Contains("train.minutes") && Contains("1,5"));
  CHECK_THAT(r.output, !Contains("got '5'"));
}

TEST_CASE(
    "the camera fit refuses with --require-fit a capture it cannot judge: without it the capture is reconstructed "
    "unjudged",
    "[safe][hostile][cli][camera-fit]") {
  test::Scratch s("hostile_require_fit_unjudged");
  const auto camera = test::source_dir() / "configs" / "cameras" / "flatnet_prototype" / "camera.yaml";
  std::filesystem::create_directories(s.dir / "in");
  write_gray16(s.dir / "in" / "white.png", torch::full({1024, 1280}, 65535, torch::kInt32));  // every pixel clipped
  const auto strict = test::run_flatnet("recon --camera " + q(camera) + " --input " + q(s.dir / "in") + " --out " +
                                        q(s.dir / "strict") + " --require-fit");
  CHECK(strict.code == 2);
  CHECK_THAT(strict.output, Contains("white.png") && Contains("cannot be judged") && Contains("full scale"));
  CHECK_FALSE(std::filesystem::exists(s.dir / "strict" / "white.png"));
  const auto plain =
      test::run_flatnet("recon --camera " + q(camera) + " --input " + q(s.dir / "in") + " --out " + q(s.dir / "plain"));
  CHECK(plain.code == 0);
  CHECK_THAT(plain.output, Contains("not judged"));
}

TEST_CASE("a camera whose window is no larger than its scene reconstructs without a camera fit with noise keys or not",
          "[safe][hostile][cli][camera-fit]") {
  test::Scratch s("hostile_fit_unmeasurable");
  auto gen = at::detail::createCPUGenerator(5);
  save_calibration(s.dir / "calib.mat",
                   {at::randn({4, 16, 16}, gen).to(torch::kFloat64), at::randn({4, 16, 16}, gen).to(torch::kFloat64)});
  write_file(s.dir / "camera.yaml",
             "name: square\nraw_height: 32\nraw_width: 32\nadc_bits: 10\ncrop: [0, 0, 16, 16]\nscene_size: 16\n"
             "calibration: calib.mat\nnoise_gain: 2.5e-5\nnoise_floor: 9e-8\ndark: 0.02\n");
  std::filesystem::create_directories(s.dir / "in");
  write_gray16(s.dir / "in" / "frame.png", (at::rand({32, 32}, gen) * 60000).to(torch::kInt32));
  const auto r = test::run_flatnet("recon --camera " + q(s.dir / "camera.yaml") + " --input " + q(s.dir / "in") +
                                   " --out " + q(s.dir / "out"));
  INFO(r.output);
  CHECK(r.code == 0);
  CHECK(std::filesystem::exists(s.dir / "out" / "frame.png"));
  const auto strict = test::run_flatnet("recon --camera " + q(s.dir / "camera.yaml") + " --input " + q(s.dir / "in") +
                                        " --out " + q(s.dir / "strict") + " --require-fit");
  CHECK(strict.code == 2);
  CHECK_THAT(strict.output, Contains("too small"));
}

TEST_CASE("an absurd but in-range camera geometry is refused by the captures' size before anything is built",
          "[safe][hostile][cli]") {
  test::Scratch s("hostile_absurd_geometry");
  // A 65536x65536 raw frame and a 4096-pixel scene: inside every range, and the reference camera's
  // calibration named. The calibration's SVDs and the camera fit would take gigabytes; the captures'
  // headers say first that they come from another sensor.
  write_file(s.dir / "camera.yaml",
             "name: absurd\nraw_height: 65536\nraw_width: 65536\nadc_bits: 10\n"
             "crop: [0, 0, 32000, 32000]\nscene_size: 4096\ncalibration: " +
                 test::calib_path().string() + "\n");
  std::filesystem::create_directories(s.dir / "in");
  auto gen = at::detail::createCPUGenerator(3);
  write_gray16(s.dir / "in" / "frame.png", (at::rand({1024, 1280}, gen) * 60000).to(torch::kInt32));
  for (const std::string command : {"recon --method tikhonov", "recon --method tv"}) {
    INFO(command);
    const auto r = test::run_flatnet(command + " --camera " + q(s.dir / "camera.yaml") + " --input " + q(s.dir / "in") +
                                     " --out " + q(s.dir / "out"));
    CHECK(r.code == 2);
    CHECK_THAT(r.output,
               Contains("frame.png") && Contains("raw capture is 1280x1024 (WxH), this camera gives 65536x65536"));
    CHECK_FALSE(std::filesystem::exists(s.dir / "out"));
  }
  // A capture of the wrong depth is named the same way, from its header.
  write_rgb8(s.dir / "in" / "frame.png", at::rand({3, 16, 16}, gen));
  const auto r = test::run_flatnet("recon --input " + q(s.dir / "in") + " --out " + q(s.dir / "out"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("frame.png") && Contains("single-channel"));
}
