// Camera commands: cameras, capture, capture-dataset, capture-calibration, live.
#include <iostream>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "core/util.hpp"
#include "hw/capture.hpp"
#include "hw/collect.hpp"
#include "hw/live.hpp"
#include "io/raw.hpp"
#include "optics/calibrate.hpp"
#include "recon/reconstructor.hpp"

namespace flatnet::cli {

namespace {

void add_camera_flags(cxxopts::Options& o) {
  o.add_options("camera")("device", "camera id from 'flatnet cameras' ('fake': Aravis's built-in fake camera)",
                          cxxopts::value<std::string>())(
      "camera", "camera .yaml: raw frame size (the default region) and preprocessing (default: the reference camera)",
      cxxopts::value<std::string>())("pixel-format", "e.g. Mono16, BayerRG12p (default: the camera's current one)",
                                     cxxopts::value<std::string>())(
      "exposure", "exposure time, microseconds (auto exposure is switched off)", cxxopts::value<double>())(
      "gain", "gain, dB (auto gain is switched off)", cxxopts::value<double>())(
      "frame-rate", "acquisition frame rate, Hz", cxxopts::value<double>())(
      "region", "sensor region WxH+X+Y, or 'keep' (default: the camera file's raw size at +0+0)",
      cxxopts::value<std::string>())("packet-size", "GigE Vision packet size, bytes (default: negotiated)",
                                     cxxopts::value<int64_t>()->default_value("0"))(
      "timeout-ms", "wait per frame before it counts as failed", cxxopts::value<int>()->default_value("2000"))(
      "retries", "failed frames (timeout, incomplete, disconnect) retried before giving up",
      cxxopts::value<int>()->default_value("3"));
}

std::array<int64_t, 4> parse_region(const std::string& s) {
  int64_t w = 0, h = 0, x = 0, y = 0;
  char sep1 = 0;
  std::istringstream in(s);
  in >> w >> sep1 >> h;
  require(!in.fail() && (sep1 == 'x' || sep1 == 'X') && w > 0 && h > 0, "--region",
          "expected WxH or WxH+X+Y, got '" + s + "'");
  if (in.peek() == '+') {
    char p1 = 0, p2 = 0;
    in >> p1 >> x >> p2 >> y;
    require(!in.fail() && p2 == '+' && x >= 0 && y >= 0, "--region", "expected WxH+X+Y, got '" + s + "'");
  }
  return {x, y, w, h};
}

DeviceSettings device_settings(const cxxopts::ParseResult& r, const CameraConfig& camera) {
  DeviceSettings s;
  if (r.count("pixel-format")) s.pixel_format = r["pixel-format"].as<std::string>();
  if (r.count("exposure")) s.exposure_us = r["exposure"].as<double>();
  if (r.count("gain")) s.gain_db = r["gain"].as<double>();
  if (r.count("frame-rate")) s.frame_rate = r["frame-rate"].as<double>();
  const std::string region = r.count("region") ? r["region"].as<std::string>() : "";
  if (region.empty())
    s.region = std::array<int64_t, 4>{0, 0, camera.raw.raw_width, camera.raw.raw_height};
  else if (region != "keep")
    s.region = parse_region(region);
  s.packet_size = r["packet-size"].as<int64_t>();
  s.timeout_ms = r["timeout-ms"].as<int>();
  s.retries = std::max(0, r["retries"].as<int>());
  require(s.timeout_ms > 0, "--timeout-ms", "must be positive");
  return s;
}

std::unique_ptr<FrameSource> open_from_flags(const cxxopts::ParseResult& r, const CameraConfig& camera) {
  require(r.count("device"), "--device",
          "required ('flatnet cameras' lists the connected cameras; 'fake' is Aravis's simulator)");
  return open_camera(r["device"].as<std::string>(), device_settings(r, camera));
}

void add_display_flags(cxxopts::Options& o) {
  o.add_options("display")("display", "window | none (headless: nothing is shown)",
                           cxxopts::value<std::string>()->default_value("window"))(
      "monitor", "X,Y: top-left of the monitor to use in the desktop (see xrandr)",
      cxxopts::value<std::string>()->default_value("0,0"))(
      "scale", "integer magnification of the scene on screen (0: largest that fits)",
      cxxopts::value<int>()->default_value("0"))("settle-ms", "wait after showing a scene before the frames that count",
                                                 cxxopts::value<int>()->default_value("500"));
}

DisplayOptions display_options(const cxxopts::ParseResult& r) {
  DisplayOptions d;
  d.kind = r["display"].as<std::string>();
  const auto monitor = r["monitor"].as<std::string>();
  char comma = 0;
  std::istringstream in(monitor);
  in >> d.x >> comma >> d.y;
  require(!in.fail() && comma == ',', "--monitor", "expected X,Y, got '" + monitor + "'");
  d.scale = r["scale"].as<int>();
  return d;
}

// Flags and objects every display-capture command shares.
void add_collect_flags(cxxopts::Options& o, int default_average) {
  o.add_options("collection")("average", "frames averaged per capture",
                              cxxopts::value<int>()->default_value(std::to_string(default_average)))(
      "limit", "stop after this many new captures (0: all)", cxxopts::value<int64_t>()->default_value("0"));
  add_camera_flags(o);
  add_display_flags(o);
  add_common(o);
}

struct CollectionSession {
  std::unique_ptr<FrameSource> source;
  std::unique_ptr<Display> display;
};

// Opens the camera, then the display, and starts watching for Ctrl-C.
CollectionSession open_collection(const cxxopts::ParseResult& r, const CameraConfig& camera) {
  CollectionSession s{open_from_flags(r, camera), nullptr};
  s.display = make_display(display_options(r));
  watch_interrupts();
  return s;
}

CollectOptions collect_options(const cxxopts::ParseResult& r) {
  CollectOptions c;
  c.average = r["average"].as<int>();
  c.settle_ms = r["settle-ms"].as<int>();
  c.limit = r["limit"].as<int64_t>();
  require(c.average >= 1, "--average", "must be at least 1");
  require(c.settle_ms >= 0, "--settle-ms", "must not be negative");
  return c;
}

void print_report(const CollectReport& rep, const std::string& what) {
  std::cout << what << ": " << rep.captured << " captured, " << rep.skipped << " already there, "
            << rep.total - rep.captured - rep.skipped << " to go (" << format_duration(rep.seconds) << ")\n";
}

}  // namespace

int cameras(int argc, char** argv) {
  cxxopts::Options o("flatnet cameras", "List the cameras Aravis can reach (USB3 Vision, GigE Vision).");
  o.add_options()("fake", "also list Aravis's built-in fake camera");
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  const auto list = list_cameras(r.count("fake") > 0);
  if (list.empty()) {
    std::cout
        << "no cameras found (USB: check the udev rules and permissions; GigE: same subnet, firewall; see README)\n";
    return 0;
  }
  for (const auto& d : list)
    std::cout << d.id << "  " << d.vendor << " " << d.model << "  serial " << d.serial << "  " << d.protocol
              << (d.address.empty() ? "" : " " + d.address) << "\n";
  return 0;
}

int capture(int argc, char** argv) {
  cxxopts::Options o("flatnet capture", "Capture raw frames (16-bit PNG + JSON sidecar) from a camera.");
  o.add_options()("out", "output folder", cxxopts::value<std::string>())("frames", "captures to write",
                                                                         cxxopts::value<int>()->default_value("1"))(
      "average", "frames averaged into each capture", cxxopts::value<int>()->default_value("1"))(
      "prefix", "file name prefix (PREFIX_0000.png, after any already there)",
      cxxopts::value<std::string>()->default_value("capture"));
  add_camera_flags(o);
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("out"), "capture", "--out DIR is required");
  const auto camera = camera_from(r);
  CaptureOptions opt;
  opt.out = r["out"].as<std::string>();
  opt.frames = r["frames"].as<int>();
  opt.average = r["average"].as<int>();
  opt.prefix = r["prefix"].as<std::string>();
  require(opt.average >= 1, "--average", "must be at least 1");
  auto source = open_from_flags(r, camera);
  watch_interrupts();
  const auto rep = capture_frames(*source, opt);
  std::cout << "wrote " << rep.written << " captures (" << source->format().name << ", " << source->format().bits
            << "-bit, mean of " << opt.average << ") to " << opt.out.string() << " from index " << rep.first_index
            << "; " << rep.frames_per_s << " frames/s";
  if (source->recovered_failures() > 0)
    std::cout << "; recovered from " << source->recovered_failures() << " failed frames";
  std::cout << "\n";
  return interrupted() ? 130 : 0;
}

int capture_dataset(int argc, char** argv) {
  cxxopts::Options o(
      "flatnet capture-dataset",
      "Display-capture dataset: show each photograph full screen, capture, write a FlatNet-layout pair.\n"
      "Resumable: run the same command again after an interruption.");
  o.add_options()("images", "folder of photographs", cxxopts::value<std::string>())(
      "out", "dataset folder (meas/, gt/, train_*.txt, val_*.txt)", cxxopts::value<std::string>())(
      "val-fraction", "share of photographs in the validation lists", cxxopts::value<double>()->default_value("0.1"))(
      "seed", "split seed", cxxopts::value<uint64_t>()->default_value("0"));
  add_collect_flags(o, 1);
  add_force_folder(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("images") && r.count("out"), "capture-dataset", "--images DIR and --out DIR are required");
  const auto camera = camera_from(r);
  DatasetCollectOptions opt;
  opt.out = r["out"].as<std::string>();
  const auto claim = claim_out(r, opt.out, "capture-dataset");
  opt.scene_size = camera.scene_size;
  opt.val_fraction = r["val-fraction"].as<double>();
  opt.seed = r["seed"].as<uint64_t>();
  opt.collect = collect_options(r);
  const auto images = list_images(r["images"].as<std::string>(), kImageExtensions);
  require(!images.empty(), r["images"].as<std::string>(), "no photographs (.png .jpg .tif .bmp) in this folder");
  auto session = open_collection(r, camera);
  const auto rep = collect_dataset(images, *session.source, *session.display, opt);
  print_report(rep, "capture-dataset " + opt.out.string());
  if (rep.stopped) std::cout << "run the same command again to continue\n";
  return interrupted() ? 130 : 0;
}

int capture_calibration(int argc, char** argv) {
  cxxopts::Options o(
      "flatnet capture-calibration",
      "Show the separable Hadamard calibration patterns, capture each, then calibrate (Asif et al. 2017).\n"
      "Resumable: run the same command again after an interruption.");
  o.add_options()("out", "folder for the pattern captures (NAME.png + NAME.json)", cxxopts::value<std::string>())(
      "calib-out", "calibration .mat to write once every pattern is captured (default: OUT/calib.mat)",
      cxxopts::value<std::string>())("level", "display code (sRGB, 1..255) of the patterns' bright parts",
                                     cxxopts::value<int>()->default_value(std::to_string(kDefaultPatternLevel)));
  add_collect_flags(o, 4);
  add_force_folder(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("out"), "capture-calibration", "--out DIR is required");
  const auto camera = camera_from(r);
  const std::filesystem::path out = r["out"].as<std::string>();
  const std::filesystem::path calib_out =
      r.count("calib-out") ? std::filesystem::path(r["calib-out"].as<std::string>()) : out / "calib.mat";
  const int level = r["level"].as<int>();
  std::vector<CollectItem> items;
  for (auto& p : calibration_patterns(camera.scene_size, level))
    items.push_back({p.name + ".png", [img = p.image] { return img; }});
  const auto claim = claim_out(r, out, "capture-calibration");
  auto session = open_collection(r, camera);
  const auto rep = collect(items, *session.source, *session.display, collect_options(r),
                           [&](const std::string& n) { return out / n; });
  print_report(rep, "capture-calibration " + out.string());
  if (rep.stopped) {
    std::cout << "run the same command again to continue; the calibration is computed once all " << rep.total
              << " patterns are captured\n";
    return interrupted() ? 130 : 0;
  }
  auto capture = [&](const std::string& name) { return load_centred_planes(out / (name + ".png"), camera.raw); };
  save_calibration(calib_out, estimate_calibration(camera.scene_size, capture, level));
  std::cout << "wrote " << calib_out.string() << "\n";
  return 0;
}

int live(int argc, char** argv) {
  cxxopts::Options o("flatnet live", "Live view: grab, reconstruct (Tikhonov or FlatNet), show with the frame rate.");
  o.add_options()("model", "FlatNet model file (its camera preprocessing is used)", cxxopts::value<std::string>())(
      "calib", "calibration .mat for Tikhonov (default: the camera file's)", cxxopts::value<std::string>())(
      "lambda", "Tikhonov regulariser (default: the camera file's)", cxxopts::value<double>()->default_value("0"))(
      "no-window", "print the frame rate instead of showing the reconstruction")(
      "frames", "stop after this many frames (0: until Esc, q or Ctrl-C)",
      cxxopts::value<int64_t>()->default_value("0"))("seconds", "stop after this long (0: no limit)",
                                                     cxxopts::value<double>()->default_value("0"))(
      "scale", "magnification of the reconstruction on screen", cxxopts::value<int>()->default_value("2"))(
      "require-fit", "stop (exit 2) when a frame does not fit the camera the reconstruction is for");
  add_precision(o);
  add_camera_flags(o);
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(!(r.count("model") && r.count("calib")), "live", "give --model or --calib, not both");
  ReconstructorSpec spec;
  spec.method = r.count("model") ? "flatnet" : "tikhonov";
  spec.use_camera = !r.count("model") || r.count("camera");  // a model preprocesses as it was trained
  if (spec.use_camera) spec.camera = camera_from(r);
  if (r.count("model")) spec.model = r["model"].as<std::string>();
  if (r.count("calib")) spec.calibration = r["calib"].as<std::string>();
  spec.lambda = r["lambda"].as<double>();
  spec.levers.bf16 = r.count("model") && precision_from(r) == Precision::bf16;
  auto built = make_reconstructor(spec);
  const auto& camera = built.camera;
  auto source = open_from_flags(r, camera);
  std::unique_ptr<Display> display;
  if (!r.count("no-window")) {
    DisplayOptions d;
    d.fullscreen = false;
    d.title = "flatnet live";
    d.scale = std::max(1, r["scale"].as<int>());
    display = make_display(d);
  }
  LiveOptions opt;
  opt.geometry = camera.raw;
  opt.frames = r["frames"].as<int64_t>();
  opt.seconds = r["seconds"].as<double>();
  opt.log = display ? nullptr : &std::cout;
  opt.fit = built.fit.get();
  opt.warn = &std::cerr;
  opt.require_fit = r.count("require-fit") > 0;
  require(!opt.require_fit || opt.fit, "--require-fit", "cannot judge the frames: " + built.no_fit);
  if (!opt.fit) std::cerr << "note: live: frames are not judged against the camera: " << built.no_fit << "\n";
  watch_interrupts();
  std::cout << "live: " << built.engine->describe() << ", camera " << source->describe()["device"].get<std::string>()
            << " (" << source->format().name << "); Esc, q or Ctrl-C stops\n";
  const auto s = run_live(*source, *built.engine, display.get(), opt);
  std::cout << "live: " << s.frames << " frames, " << s.fps << " fps (per frame: grab " << s.grab_ms
            << " ms, preprocess " << s.preprocess_ms << " ms, reconstruct " << s.reconstruct_ms << " ms, show "
            << s.show_ms << " ms)\n";
  if (s.fit_checks > 0) {
    std::cout << "live: camera fit measured on " << s.fit_checks << " of " << s.frames
              << " frames (one a second): " << s.misfits << " did not fit camera '"
              << printable(built.fit->camera_name()) << "'";
    if (s.misfits > 0) std::cout << " (worst fit " << std::setprecision(3) << s.worst_fit << ")";
    std::cout << "\n";
  }
  return 0;
}

}  // namespace flatnet::cli
