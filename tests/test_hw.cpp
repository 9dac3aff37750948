// Camera capture without hardware: pixel-format unpacking byte for byte, averaging and the
// collector against a scripted frame source, then Aravis's built-in fake camera (Fake_1) and its
// GigE Vision simulator (arv-fake-gv-camera-0.8, on loopback inside a private network namespace)
// through the flatnet binary: formats, averaging, sidecars, resumable datasets, calibration
// collection, live view, lost packets and a camera that disconnects and comes back.
#include "catch_torch.hpp"
#include <fstream>

#include <nlohmann/json.hpp>

#include "core/error.hpp"
#include "core/util.hpp"
#include "helpers.hpp"
#include "hw/capture.hpp"
#include "hw/collect.hpp"
#include "hw/display.hpp"
#include "hw/pixel_format.hpp"
#include "io/dataset.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"

using namespace flatnet;
using Catch::Matchers::Contains;

namespace {

using test::q;

std::vector<uint8_t> bytes_of(const torch::Tensor& codes, const std::string& format) {
  return pack_frame(codes, describe_pixel_format(format));
}

torch::Tensor unpack(const std::vector<uint8_t>& b, int64_t w, int64_t h, const std::string& format) {
  return unpack_frame(b.data(), b.size(), w, h, describe_pixel_format(format));
}

// A scripted camera: frame i has every code equal to codes[i]; timestamps 1 ms apart from `t0`.
class ScriptedSource final : public FrameSource {
 public:
  ScriptedSource(std::vector<int> codes, int64_t h, int64_t w) : codes_(std::move(codes)), h_(h), w_(w) {
    format_ = describe_pixel_format("Mono12");
  }
  Frame next_frame(Clock::time_point) override {
    require(next_ < codes_.size(), "scripted", "out of frames");
    Frame f;
    f.codes = torch::full({h_, w_}, codes_[next_], torch::kInt32);
    f.frame_id = next_++;
    return f;
  }
  Frame latest_frame() override { return next_frame({}); }
  const PixelFormatInfo& format() const override { return format_; }
  nlohmann::json describe() const override { return {{"device", "scripted"}}; }
  int64_t recovered_failures() const override { return 0; }
  size_t used() const { return next_; }

 private:
  std::vector<int> codes_;
  int64_t h_, w_;
  size_t next_ = 0;
  PixelFormatInfo format_;
};

bool fake_camera_available() { return have_aravis(); }

// The GigE Vision simulator needs a network namespace whose only interface is loopback: on a
// machine with other interfaces, Aravis streams to the address discovery answered on, which the
// simulator (bound to 127.0.0.1) cannot reach.
bool gv_simulator_available() {
  static const bool ok =
      have_aravis() && std::system(
                           "command -v arv-fake-gv-camera-0.8 >/dev/null 2>&1 && command -v ip >/dev/null 2>&1 && "
                           "command -v ss >/dev/null 2>&1 && "
                           "unshare -n true >/dev/null 2>&1") == 0;
  return ok;
}

// Runs `body` (a shell script) in a fresh loopback-only network namespace with the GigE Vision
// simulator (serial TST, so the device is "Aravis-Fake-TST") started first; `$CAM` is its pid and
// `start_cam` (re)starts it. Returns the exit code and the output.
test::RunResult with_gv_simulator(const std::string& simulator_args, const std::string& body) {
  const std::string script =
      "ip link set lo up\n"
      // Waits on the event, not on a clock: the simulator's GVCP port bound (at most 60 s of polls,
      // so a simulator that never starts fails the test instead of hanging it).
      "wait_bound() { i=0; until ss -lun | grep -q '127.0.0.1:3956 '; do i=$((i+1)); [ $i -gt 1200 ] && "
      "return 1; sleep 0.05; done; }\n"
      "start_cam() { arv-fake-gv-camera-0.8 -i 127.0.0.1 -s TST " +
      simulator_args +
      " >/dev/null 2>&1 & CAM=$!; wait_bound; }\n"
      "start_cam\n" +
      body + "\nrc=$?\nkill $CAM 2>/dev/null\nexit $rc\n";
  test::Scratch s("gvscript");
  std::ofstream(s.dir / "run.sh") << script;
  return test::run_shell("timeout 600 unshare -n sh " + q(s.dir / "run.sh"));
}

std::string flatnet_bin() { return FLATNET_BINARY; }

int count_files(const std::filesystem::path& dir, const std::string& ext) {
  int n = 0;
  if (!std::filesystem::exists(dir)) return 0;
  for (const auto& e : std::filesystem::directory_iterator(dir)) n += e.path().extension() == ext;
  return n;
}

bool has_temporary_files(const std::filesystem::path& dir) {
  for (const auto& e : std::filesystem::recursive_directory_iterator(dir))
    if (e.path().filename().string().find(".tmp") != std::string::npos) return true;
  return false;
}

nlohmann::json read_json(const std::filesystem::path& p) {
  std::ifstream in(p);
  REQUIRE(in.good());
  return nlohmann::json::parse(in);
}

}  // namespace

TEST_CASE("pixel formats: what flatnet can store, and why not", "[hw][unit]") {
  CHECK(describe_pixel_format("Mono8").bits == 8);
  CHECK(describe_pixel_format("Mono16").packing == Packing::u16);
  const auto rg12p = describe_pixel_format("BayerRG12p");
  CHECK(rg12p.bits == 12);
  CHECK(rg12p.packing == Packing::lsb_packed);
  CHECK(rg12p.bayer == "RG");
  CHECK(describe_pixel_format("Mono12Packed").packing == Packing::gev_packed);
  CHECK(describe_pixel_format("BayerGB10").packing == Packing::u16);
  CHECK(describe_pixel_format("Mono10p").frame_bytes(5, 3) == 19);       // ceil(15 * 10 / 8)
  CHECK(describe_pixel_format("Mono12Packed").frame_bytes(5, 3) == 24);  // 8 pairs of 3 bytes
  CHECK_THROWS_WITH(describe_pixel_format("RGB8"), Contains("not a raw mosaic"));
  CHECK_THROWS_WITH(describe_pixel_format("YUV422_8"), Contains("not a raw mosaic"));
  CHECK_THROWS_WITH(describe_pixel_format("Mono32"), Contains("do not fit a 16-bit PNG"));
  CHECK_THROWS_WITH(describe_pixel_format("Mono12Foo"), Contains("unsupported packing"));
  // Digits past an int's range are no bit depth (std::stoi threw "stoi", issue 113).
  CHECK_THROWS_WITH(describe_pixel_format("Mono99999999999"), Contains("Mono99999999999") && Contains("unrecognised"));
}

TEST_CASE("packed pixels unpack to the codes the specifications define", "[hw][unit]") {
  // Two pixels, p0 = 0xABC and p1 = 0x123, written by hand from the specifications.
  const auto expected = torch::tensor({{0xABC, 0x123}}, torch::kInt32);
  // PFNC Mono12p: one LSB-first bit stream: p0 in bits 0..11, p1 in bits 12..23.
  CHECK(torch::equal(unpack({0xBC, 0x3A, 0x12}, 2, 1, "Mono12p"), expected));
  // GigE Vision Mono12Packed: B0 = p0[11:4], B1 = p1[3:0] << 4 | p0[3:0], B2 = p1[11:4].
  CHECK(torch::equal(unpack({0xAB, 0x3C, 0x12}, 2, 1, "Mono12Packed"), expected));
  // Mono10Packed: B0 = p0[9:2], B1 = p1[1:0] << 4 | p0[1:0], B2 = p1[9:2]; p0 = 0x2BD, p1 = 0x0C6.
  CHECK(torch::equal(unpack({0xAF, 0x21, 0x31}, 2, 1, "Mono10Packed"), torch::tensor({{0x2BD, 0x0C6}}, torch::kInt32)));
  // Mono16: little-endian.
  CHECK(torch::equal(unpack({0x34, 0x12}, 1, 1, "Mono16"), torch::tensor({{0x1234}}, torch::kInt32)));
}

TEST_CASE("every storable packing round-trips, odd pixel counts included", "[hw][unit]") {
  for (const std::string f : {"Mono8", "BayerBG8", "Mono10", "Mono12", "Mono14", "Mono16", "BayerRG10p", "Mono12p",
                              "Mono10Packed", "BayerGR12Packed"}) {
    const auto info = describe_pixel_format(f);
    const auto codes = torch::randint(0, 1 << info.bits, {3, 5}, torch::kInt32);  // 15 pixels: odd
    INFO(f);
    CHECK(torch::equal(unpack(bytes_of(codes, f), 5, 3, f), codes));
  }
}

TEST_CASE("a short buffer is refused, never read past its end", "[hw][unit]") {
  std::vector<uint8_t> b(10, 0);
  CHECK_THROWS_WITH(unpack(b, 4, 3, "Mono8"), Contains("incomplete frame: 10 bytes") && Contains("needs 12"));
}

TEST_CASE("stored values put the ADC's bits at the top, averaging keeps fractions", "[hw][unit]") {
  const auto stored = codes_to_stored(torch::tensor({0.0, 1.0, 1023.0, 0.5}, torch::kFloat64), 10);
  CHECK(torch::equal(stored, torch::tensor({0, 64, 65472, 32}, torch::kInt32)));
  CHECK(codes_to_stored(torch::tensor({255.0}, torch::kFloat64), 8).item<int>() == 65280);
  CHECK(codes_to_stored(torch::tensor({65535.0}, torch::kFloat64), 16).item<int>() == 65535);
}

TEST_CASE("averaging is the exact mean of K frames, and the capture and its sidecar land together", "[hw][unit]") {
  ScriptedSource source({100, 101, 103, 200}, 4, 6);
  std::vector<uint64_t> ids;
  const auto mean = average_frames(source, 3, {}, &ids);
  CHECK(mean.scalar_type() == torch::kFloat64);
  CHECK(mean[0][0].item<double>() == Approx(304.0 / 3).epsilon(1e-12));
  CHECK(ids == std::vector<uint64_t>{0, 1, 2});
  test::Scratch s("hw_avg");
  write_raw_capture(s.dir / "c.png", mean, source.format(), capture_sidecar(source, 3, ids));
  const auto stored = read_gray16(s.dir / "c.png");                 // {H,W}
  CHECK(stored[2][3].item<float>() == std::round(304.0 / 3 * 16));  // 12-bit codes << 4
  const auto j = read_json(s.dir / "c.json");
  CHECK(j["frames_averaged"] == 3);
  CHECK(j["stored_scale"] == 16);
  CHECK(j["device"] == "scripted");
}

TEST_CASE("the collector resumes: done items are not captured again, lists name complete pairs", "[hw][unit]") {
  test::Scratch s("hw_collect");
  auto photos = s.dir / "photos";
  std::filesystem::create_directories(photos);
  for (int i = 0; i < 5; ++i) write_rgb8(photos / ("p" + std::to_string(i) + ".png"), torch::rand({3, 20, 24}));
  auto display = make_display({"none"});
  DatasetCollectOptions opt;
  opt.out = s.dir / "ds";
  opt.scene_size = 16;
  opt.val_fraction = 0.4;
  opt.collect.settle_ms = 0;
  opt.collect.limit = 3;
  opt.collect.progress = false;
  const auto images = list_images(photos, kImageExtensions);
  ScriptedSource first(std::vector<int>(10, 7), 8, 10);
  const auto a = collect_dataset(images, first, *display, opt);
  CHECK(a.captured == 3);
  CHECK(a.stopped);
  CHECK(first.used() == 3);
  const auto listed = read_lines(opt.out / "train_meas.txt").size() + read_lines(opt.out / "val_meas.txt").size();
  CHECK(listed == 3);  // only complete pairs are listed
  opt.collect.limit = 0;
  ScriptedSource second(std::vector<int>(10, 9), 8, 10);
  const auto b = collect_dataset(images, second, *display, opt);
  CHECK(b.skipped == 3);
  CHECK(b.captured == 2);
  CHECK(!b.stopped);
  CHECK(second.used() == 2);  // nothing captured twice
  CHECK(display->shown() == 5);
  const auto train = read_pairs(split_lists(opt.out, "train")), val = read_pairs(split_lists(opt.out, "val"));
  CHECK(train.size() == 3);
  CHECK(val.size() == 2);
  CHECK(read_rgb(opt.out / "gt" / "p0.png").size(1) == 16);
  CHECK(!has_temporary_files(opt.out));
}

TEST_CASE("scenes are magnified by whole pixels and centred on black", "[hw][unit]") {
  auto img = torch::zeros({3, 2, 2});
  img[0][0][0] = 1;                                    // red top-left pixel
  const auto canvas = compose_canvas(img, 10, 12, 0);  // scale 5 fits 10 rows; 1 column of black each side
  CHECK(canvas.sizes() == torch::IntArrayRef({10, 12, 3}));
  CHECK(canvas[0][1][2].item<int>() == 255);  // BGR: red is channel 2
  CHECK(canvas[4][5][2].item<int>() == 255);
  CHECK(canvas[5][6][2].item<int>() == 0);
  CHECK(canvas[0][0][2].item<int>() == 0);  // the black border
}

TEST_CASE("fake camera: formats, averaging, sidecars, refusals", "[hw][fake][solo]") {
  if (!fake_camera_available()) {
    SKIP_TEST("built without Aravis");
  }
  test::Scratch s("hw_fake");
  const auto tiny = q(test::data_dir() / "cameras" / "tiny.yaml");
  auto r = test::run_flatnet("cameras --fake");
  CHECK(r.code == 0);
  CHECK_THAT(r.output, Contains("Fake_1"));

  r = test::run_flatnet("capture --device fake --camera " + tiny +
                        " --pixel-format Mono8 --frames 2 --average 3 --out " + q(s.dir / "m8"));
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("wrote 2 captures (Mono8, 8-bit, mean of 3)"));
  const auto j = read_json(s.dir / "m8" / "capture_0001.json");
  CHECK(j["pixel_format"] == "Mono8");
  CHECK(j["frames_averaged"] == 3);
  CHECK(j["frame_ids"].size() == 3);
  CHECK(j["region"]["width"] == 160);
  CHECK(j["region"]["height"] == 128);
  // The capture reads back through the raw loader with the camera's geometry.
  CameraConfig cam = load_camera_config(test::data_dir() / "cameras" / "tiny.yaml");
  const auto planes = load_capture(s.dir / "m8" / "capture_0000.png", cam.raw).planes;
  CHECK(planes.sizes() == torch::IntArrayRef({4, 60, 76}));

  // Single 8-bit frames are stored as code * 256 exactly.
  r = test::run_flatnet("capture --device fake --camera " + tiny + " --pixel-format BayerRG8 --out " + q(s.dir / "b8"));
  REQUIRE(r.code == 0);
  const auto stored = read_gray16(s.dir / "b8" / "capture_0000.png");
  CHECK(torch::equal(torch::remainder(stored, 256), torch::zeros_like(stored)));
  CHECK(read_json(s.dir / "b8" / "capture_0000.json")["bayer"] == "RG");
  // A second run numbers after the first, never overwriting it.
  r = test::run_flatnet("capture --device fake --camera " + tiny + " --pixel-format Mono16 --out " + q(s.dir / "b8"));
  REQUIRE(r.code == 0);
  CHECK(std::filesystem::exists(s.dir / "b8" / "capture_0001.png"));

  // Refused, with exit code 2 and a message that says why; nothing is written.
  const std::vector<std::pair<std::string, std::string>> refusals = {
      {"--camera " + tiny + " --pixel-format RGB8", "RGB8: not a raw mosaic format"},
      {"--camera " + tiny + " --pixel-format Mono12p", "Mono12p not offered"},
      {"--camera " + tiny + " --pixel-format Mono12p", "RGB8 (not storable)"},
      {"--region 4000x4000", "exceeds the sensor"},
      {"--exposure 1", "exposure 1.0"},
  };
  for (const auto& [flags, message] : refusals) {
    r = test::run_flatnet("capture --device fake " + flags + " --out " + q(s.dir / "x"));
    INFO(flags);
    CHECK(r.code == 2);
    CHECK_THAT(r.output, Contains(message));
  }
  r = test::run_flatnet("capture --device nosuchcamera --out " + q(s.dir / "x"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("camera nosuchcamera: cannot open"));
  CHECK(count_files(s.dir / "x", ".png") == 0);
}

TEST_CASE("fake camera: a display-capture dataset survives an interruption and reads as a training set",
          "[hw][fake][solo]") {
  if (!fake_camera_available()) {
    SKIP_TEST("built without Aravis");
  }
  test::Scratch s("hw_dataset");
  const auto tiny = q(test::data_dir() / "cameras" / "tiny.yaml");
  const auto photos = s.dir / "photos";
  std::filesystem::create_directories(photos);
  for (int i = 0; i < 6; ++i) write_rgb8(photos / ("img" + std::to_string(i) + ".png"), torch::rand({3, 40, 40}));
  const std::string base = "capture-dataset --device fake --camera " + tiny +
                           " --pixel-format Mono16 --display none --images " + q(photos) + " --out " + q(s.dir / "ds") +
                           " --val-fraction 0.34";
  // Ctrl-C half-way: the current pair is finished, nothing half-written stays.
  const std::string cmd = flatnet_bin() + " " + base + " --settle-ms 400 > " + q(s.dir / "log1") +
                          " 2>&1 & P=$!; for i in $(seq 300); do ls " + q(s.dir / "ds" / "meas") +
                          "/*.png >/dev/null 2>&1 && break; sleep 0.1; done; kill -INT $P; wait $P";
  CHECK(test::run_shell("bash -c " + q(cmd)).code == 130);
  const int first = count_files(s.dir / "ds" / "meas", ".png");
  CHECK(first >= 1);
  CHECK(first < 6);
  CHECK(!has_temporary_files(s.dir / "ds"));
  std::map<std::string, nlohmann::json> before;
  for (const auto& e : std::filesystem::directory_iterator(s.dir / "ds" / "meas"))
    if (e.path().extension() == ".json") before[e.path().filename().string()] = read_json(e.path());

  auto r = test::run_flatnet(base + " --settle-ms 0");
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output,
             Contains(std::to_string(6 - first) + " captured, " + std::to_string(first) + " already there, 0 to go"));
  for (const auto& [name, j] : before) CHECK(read_json(s.dir / "ds" / "meas" / name) == j);  // not captured again
  CHECK(read_pairs(split_lists(s.dir / "ds", "train")).size() == 4);
  CHECK(read_pairs(split_lists(s.dir / "ds", "val")).size() == 2);
}

TEST_CASE("fake camera: calibration collection, then the calibration", "[hw][fake][solo]") {
  if (!fake_camera_available()) {
    SKIP_TEST("built without Aravis");
  }
  test::Scratch s("hw_calib");
  const auto tiny = q(test::data_dir() / "cameras" / "tiny.yaml");
  const std::string base = "capture-calibration --device fake --camera " + tiny +
                           " --pixel-format Mono16 --display none --settle-ms 0 --average 1 --frame-rate 200 --out " +
                           q(s.dir / "cal");
  auto r = test::run_flatnet(base + " --limit 10");
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("10 captured, 0 already there, 118 to go"));
  CHECK(!std::filesystem::exists(s.dir / "cal" / "calib.mat"));
  r = test::run_flatnet(base);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("118 captured, 10 already there, 0 to go"));
  CHECK(std::filesystem::exists(s.dir / "cal" / "calib.mat"));
  CHECK(std::filesystem::exists(s.dir / "cal" / "col_000_pos.png"));
}

TEST_CASE("fake camera: live view with Tikhonov and with a FlatNet model", "[hw][fake][solo]") {
  if (!fake_camera_available()) {
    SKIP_TEST("built without Aravis");
  }
  auto r = test::run_flatnet("live --device fake --no-window --frames 6 --frame-rate 100");
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("Tikhonov") && Contains("live: 6 frames"));
  // The fake camera's test pattern is no FlatCam capture: the camera fit says so, once, and counts it.
  CHECK_THAT(r.output, Contains("warning: live: frame 1 does not fit camera 'sim'") &&
                           Contains("camera fit measured on 1 of 6 frames (one a second): 1 did not fit"));
  r = test::run_flatnet("live --device fake --no-window --frames 6 --frame-rate 100 --require-fit");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("--require-fit: frame 1 does not fit camera 'sim'"));
  r = test::run_flatnet("live --device fake --no-window --frames 2 --model " +
                        q(test::source_dir() / "models" / "flatnet-sim-transpose.flatnet"));
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("FlatNet") && Contains("live: 2 frames"));
  r = test::run_flatnet("live --device fake --no-window --frames 2 --region 640x480");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("frames are 640x480 but the camera file expects 1280x1024"));
  r = test::run_flatnet("live --device fake --frames 2");  // no display server in the test environment
  if (!std::getenv("DISPLAY")) {
    CHECK(r.code == 2);
    CHECK_THAT(r.output, Contains("no display server"));
  }
}

TEST_CASE("fake camera: scenes shown in a real window (Xvfb)", "[hw][fake][window][solo]") {
  if (!fake_camera_available() || std::system("command -v xvfb-run >/dev/null 2>&1") != 0) {
    SKIP_TEST("Aravis or xvfb-run missing");
  }
  test::Scratch s("hw_window");
  const auto photos = s.dir / "photos";
  std::filesystem::create_directories(photos);
  for (int i = 0; i < 2; ++i) write_rgb8(photos / ("w" + std::to_string(i) + ".png"), torch::rand({3, 30, 30}));
  const std::string cmd = "xvfb-run -a -s '-screen 0 800x600x24' " + flatnet_bin() +
                          " capture-dataset --device fake --camera " + q(test::data_dir() / "cameras" / "tiny.yaml") +
                          " --settle-ms 50 --images " + q(photos) + " --out " + q(s.dir / "ds") + " > " +
                          q(s.dir / "log") + " 2>&1";
  CHECK(std::system(cmd.c_str()) == 0);
  CHECK(count_files(s.dir / "ds" / "meas", ".png") == 2);
}

TEST_CASE("GigE Vision simulator: capture, lost packets, a camera that goes and comes back", "[hw][gv][slow]") {
  if (!gv_simulator_available()) {
    SKIP_TEST("needs Aravis, arv-fake-gv-camera-0.8, iproute2 and 'unshare -n' (root or user namespaces)");
  }
  test::Scratch s("hw_gv");
  const std::string cap = flatnet_bin() + " capture --device Aravis-Fake-TST --region 320x256 --pixel-format Mono16 ";
  auto r =
      with_gv_simulator("", flatnet_bin() + " cameras && " + cap + "--frames 2 --average 2 --out " + q(s.dir / "ok"));
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Contains("Aravis-Fake-TST") && Contains("GigEVision 127.0.0.1"));
  CHECK(count_files(s.dir / "ok", ".png") == 2);
  CHECK(read_json(s.dir / "ok" / "capture_0000.json")["protocol"] == "GigEVision");

  // Every packet lost: bounded retries, a clear error, no file.
  r = with_gv_simulator("-r 1000", cap + "--timeout-ms 300 --retries 2 --out " + q(s.dir / "lost"));
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("no complete frame after 3 attempts"));
  CHECK(count_files(s.dir / "lost", ".png") == 0);

  // The camera disappears mid-run (after the first frame is on disk) and comes back: the capture
  // reconnects and finishes.
  const auto first_frame = [&](const std::string& dir) {
    return " & P=$!; for i in $(seq 300); do [ -e " + q(s.dir / dir / "capture_0000.png") +
           " ] && break; sleep 0.1; done; ";
  };
  // The camera comes back once the capture has noticed it gone (its first retry), whatever the load.
  const auto log = q(s.dir / "back.log");
  r = with_gv_simulator("", cap + "--frames 30 --timeout-ms 500 --retries 6 --out " + q(s.dir / "back") + " > " + log +
                                " 2>&1" + first_frame("back") + "kill $CAM; i=0; until grep -q '(retry ' " + log +
                                "; do i=$((i+1)); [ $i -gt 1200 ] && break; sleep 0.05; done; start_cam; " +
                                "wait $P; rc=$?; cat " + log + "; (exit $rc)");
  CHECK(r.code == 0);
  CHECK_THAT(r.output, Contains("reconnected") && Contains("wrote 30 captures"));
  CHECK(count_files(s.dir / "back", ".png") == 30);
  for (int i = 0; i < 30; ++i) {
    char name[32];
    std::snprintf(name, sizeof name, "capture_%04d.png", i);
    CHECK(read_gray16(s.dir / "back" / name).size(1) == 320);
  }

  // The camera disappears for good: the run stops with an error; what was written is whole.
  r = with_gv_simulator("", cap + "--frames 200 --timeout-ms 300 --retries 2 --out " + q(s.dir / "gone") +
                                first_frame("gone") + "kill $CAM; wait $P");
  CHECK(r.code == 2);
  CHECK_THAT(r.output, Contains("no complete frame"));
  REQUIRE(std::filesystem::exists(s.dir / "gone"));
  CHECK(!has_temporary_files(s.dir / "gone"));
  for (const auto& e : std::filesystem::directory_iterator(s.dir / "gone"))
    if (e.path().extension() == ".png") CHECK(read_gray16(e.path()).size(0) == 256);
}
