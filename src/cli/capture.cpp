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

// The camera's flags: its settings (hw/camera_device.hpp) with what picks the camera and its frame.
struct DeviceFlags : DeviceSettings {
  std::string device;            // an id from `flatnet cameras`, or fake
  std::filesystem::path camera;  // the camera file (camera_from reads the flag)
  std::string region_text;       // --region: WxH+X+Y, keep, or empty: the camera file's raw size at +0+0
};

// A setting the camera keeps unless given (std::optional): a finite number within [lo, hi].
template <std::optional<double> DeviceSettings::*member, int lo, int hi>
void set_optional(DeviceFlags& s, const std::string& text) {
  char* end = nullptr;
  const double value = std::strtod(text.c_str(), &end);
  if (text.empty() || *end != 0 || !std::isfinite(value) || value < lo || value > hi || (lo == 0 && value == 0))
    throw std::invalid_argument("expected a number in " + std::string(lo == 0 ? "(" : "[") + std::to_string(lo) + ", " +
                                std::to_string(hi) + "]");
  s.*member = value;
}
template <std::optional<double> DeviceSettings::*member>
std::string optional_text(const DeviceFlags& s) {
  if (!(s.*member)) return "";
  std::ostringstream os;
  os << *(s.*member);
  return os.str();
}

const FlagTable<DeviceFlags>& device_flags() {
  using S = DeviceFlags;
  static const FlagTable<S> rows = {
      {"device", &S::device, "camera id from 'flatnet cameras' ('fake': Aravis's built-in fake camera)"},
      {"camera", &S::camera,
       "camera .yaml: raw frame size (the default region) and preprocessing (default: the reference camera)"},
      {"pixel-format", static_cast<std::string S::*>(&DeviceSettings::pixel_format),
       "e.g. Mono16, BayerRG12p (default: the camera's current one)"},
      {"exposure",
       FlagText<S>{set_optional<&DeviceSettings::exposure_us, 0, 100000000>,
                   optional_text<&DeviceSettings::exposure_us>},
       "exposure time, microseconds, in (0, 1e8] (auto exposure is switched off; default: the camera's)"},
      {"gain", FlagText<S>{set_optional<&DeviceSettings::gain_db, -100, 100>, optional_text<&DeviceSettings::gain_db>},
       "gain, dB, in [-100, 100] (auto gain is switched off; default: the camera's)"},
      {"frame-rate",
       FlagText<S>{set_optional<&DeviceSettings::frame_rate, 0, 1000000>, optional_text<&DeviceSettings::frame_rate>},
       "acquisition frame rate, Hz, in (0, 1e6] (default: the camera's)"},
      {"region", &S::region_text, "sensor region WxH+X+Y, or 'keep' (default: the camera file's raw size at +0+0)"},
      {"packet-size", static_cast<int64_t S::*>(&DeviceSettings::packet_size),
       "GigE Vision packet size, bytes (0: negotiated)", 0, 65536, "0 to 65536"},
      {"timeout-ms", static_cast<int S::*>(&DeviceSettings::timeout_ms), "wait per frame before it counts as failed", 1,
       1e7, "a positive wait"},
      {"retries", static_cast<int S::*>(&DeviceSettings::retries),
       "failed frames (timeout, incomplete, disconnect) retried before giving up", 0, 1e6, "0 or more"},
  };
  return rows;
}

void set_monitor(DisplayOptions& d, const std::string& text) {
  char comma = 0;
  std::istringstream in(text);
  in >> d.x >> comma >> d.y;
  if (in.fail() || comma != ',') throw std::invalid_argument("expected X,Y");
}
std::string monitor_text(const DisplayOptions& d) { return std::to_string(d.x) + "," + std::to_string(d.y); }

const FlagTable<DisplayOptions>& display_flags() {
  using S = DisplayOptions;
  static const FlagTable<S> rows = {
      {"display", &S::kind, "window | none (headless: nothing is shown)"},
      {"monitor", FlagText<S>{set_monitor, monitor_text},
       "X,Y: top-left of the monitor to use in the desktop (see xrandr)"},
      {"scale", &S::scale, "integer magnification of the scene on screen (0: largest that fits)", 0, 64, "0 to 64"},
  };
  return rows;
}

// A display-capture collection's settings; `Average` sets how many frames each capture averages by
// default (a photograph 1, a calibration pattern 4).
template <int Average>
struct CollectSettings : CollectOptions {
  CollectSettings() { average = Average; }
};

template <class S>
const FlagTable<S>& collect_flags() {
  static const FlagTable<S> rows = {
      {"average", static_cast<int S::*>(&CollectOptions::average), "frames averaged per capture", 1, 100000,
       "at least 1 frame"},
      {"limit", static_cast<int64_t S::*>(&CollectOptions::limit), "stop after this many new captures (0: all)", 0,
       1e12, "0 (all) or more"},
      {"settle-ms", static_cast<int S::*>(&CollectOptions::settle_ms),
       "wait after showing a scene before the frames that count", 0, 1e7, "0 or more"},
  };
  return rows;
}
using PhotoCollect = CollectSettings<1>;
using PatternCollect = CollectSettings<4>;

void add_camera_flags(cxxopts::Options& o) { add_flags(o, device_flags(), "camera"); }

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

std::unique_ptr<FrameSource> open_from_flags(const cxxopts::ParseResult& r, const CameraConfig& camera) {
  DeviceFlags s;
  read_flags(r, device_flags(), s);
  require(!s.device.empty(), "--device",
          "required ('flatnet cameras' lists the connected cameras; 'fake' is Aravis's simulator)");
  if (s.region_text.empty())
    s.region = std::array<int64_t, 4>{0, 0, camera.raw.raw_width, camera.raw.raw_height};
  else if (s.region_text != "keep")
    s.region = parse_region(s.region_text);
  return open_camera(s.device, s);
}

DisplayOptions display_options(const cxxopts::ParseResult& r) {
  DisplayOptions d;
  read_flags(r, display_flags(), d);
  return d;
}

// Flags and objects every display-capture command shares (S: PhotoCollect or PatternCollect).
template <class S>
void add_collect_flags(cxxopts::Options& o) {
  add_flags(o, collect_flags<S>(), "collection");
  add_camera_flags(o);
  add_flags(o, display_flags(), "display");
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

template <class S>
CollectOptions collect_options(const cxxopts::ParseResult& r) {
  S c;
  read_flags(r, collect_flags<S>(), c);
  return c;
}

const FlagTable<CaptureOptions>& capture_flags() {
  using S = CaptureOptions;
  static const FlagTable<S> rows = {
      {"out", &S::out, "output folder"},
      {"frames", &S::frames, "captures to write", 1, 1e9, "at least 1"},
      {"average", &S::average, "frames averaged into each capture", 1, 100000, "at least 1 frame"},
      {"prefix", &S::prefix, "file name prefix (PREFIX_0000.png, after any already there)"},
  };
  return rows;
}

// capture-dataset's settings: the photographs and the collection's options.
struct PhotoDatasetSettings : DatasetCollectOptions {
  std::filesystem::path images;
};

const FlagTable<PhotoDatasetSettings>& capture_dataset_flags() {
  using S = PhotoDatasetSettings;
  static const FlagTable<S> rows = {
      {"images", &S::images, "folder of photographs"},
      {"out", static_cast<std::filesystem::path S::*>(&DatasetCollectOptions::out),
       "dataset folder (meas/, gt/, train_*.txt, val_*.txt)"},
      {"val-fraction", static_cast<double S::*>(&DatasetCollectOptions::val_fraction),
       "share of photographs in the validation lists", 0, 1, "0 to 1"},
      {"seed", static_cast<uint64_t S::*>(&DatasetCollectOptions::seed), "split seed"},
  };
  return rows;
}

struct PatternSettings {
  std::filesystem::path out, calib_out;
  int level = kDefaultPatternLevel;
};

const FlagTable<PatternSettings>& pattern_flags() {
  static const FlagTable<PatternSettings> rows = {
      {"out", &PatternSettings::out, "folder for the pattern captures (NAME.png + NAME.json)"},
      {"calib-out", &PatternSettings::calib_out,
       "calibration .mat to write once every pattern is captured (default: OUT/calib.mat)"},
      {"level", &PatternSettings::level, "display code (sRGB) of the patterns' bright parts", 1, 255, "1 to 255"},
  };
  return rows;
}

struct CamerasSettings {
  bool fake = false;
};

const FlagTable<CamerasSettings>& cameras_flags() {
  static const FlagTable<CamerasSettings> rows = {
      {"fake", &CamerasSettings::fake, "also list Aravis's built-in fake camera"},
  };
  return rows;
}

// `flatnet live`'s window and run length.
struct LiveSettings {
  std::filesystem::path model, calib;
  bool no_window = false, require_fit = false;
  double lambda = ReconstructorSpec{}.lambda;
  int scale = 2;
  int64_t frames = LiveOptions{}.frames;
  double seconds = LiveOptions{}.seconds;
};

const FlagTable<LiveSettings>& live_flags() {
  using S = LiveSettings;
  static const FlagTable<S> rows = {
      {"model", &S::model, "FlatNet model file (its camera preprocessing is used)"},
      {"calib", &S::calib, "calibration .mat for Tikhonov (default: the camera file's)"},
      {"no-window", &S::no_window, "print the frame rate instead of showing the reconstruction"},
      {"require-fit", &S::require_fit, "stop (exit 2) when a frame does not fit the camera the reconstruction is for"},
      {"lambda", &S::lambda, "Tikhonov regulariser (0: the camera file's)", 1e-12, 1e6,
       "a positive regulariser (leave it out for the camera file's)"},
      {"frames", &S::frames, "stop after this many frames (0: until Esc, q or Ctrl-C)", 0, 1e12,
       "0 (no limit) or more"},
      {"seconds", &S::seconds, "stop after this long (0: no limit)", 0, 1e7, "0 (no limit) or more"},
      {"scale", &S::scale, "magnification of the reconstruction on screen", 1, 64, "1 to 64"},
  };
  return rows;
}

void print_report(const CollectReport& rep, const std::string& what) {
  std::cout << what << ": " << rep.captured << " captured, " << rep.skipped << " already there, "
            << rep.total - rep.captured - rep.skipped << " to go (" << format_duration(rep.seconds) << ")\n";
}

}  // namespace

int cameras(int argc, char** argv) {
  cxxopts::Options o("flatnet cameras", "List the cameras Aravis can reach (USB3 Vision, GigE Vision).");
  add_flags(o, cameras_flags());
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  CamerasSettings settings;
  read_flags(r, cameras_flags(), settings);
  const auto list = list_cameras(settings.fake);
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
  add_flags(o, capture_flags());
  add_camera_flags(o);
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("out"), "capture", "--out DIR is required");
  const auto camera = camera_from(r);
  CaptureOptions opt;
  read_flags(r, capture_flags(), opt);
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
  add_flags(o, capture_dataset_flags());
  add_collect_flags<PhotoCollect>(o);
  add_force_folder(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("images") && r.count("out"), "capture-dataset", "--images DIR and --out DIR are required");
  const auto camera = camera_from(r);
  PhotoDatasetSettings opt;
  read_flags(r, capture_dataset_flags(), opt);
  const auto claim = claim_out(r, opt.out, "capture-dataset");
  opt.scene_size = camera.scene_size;
  opt.collect = collect_options<PhotoCollect>(r);
  const auto images = list_images(opt.images, kImageExtensions);
  require(!images.empty(), opt.images, "no photographs (.png .jpg .tif .bmp) in this folder");
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
  add_flags(o, pattern_flags());
  add_collect_flags<PatternCollect>(o);
  add_force_folder(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("out"), "capture-calibration", "--out DIR is required");
  const auto camera = camera_from(r);
  PatternSettings pattern;
  read_flags(r, pattern_flags(), pattern);
  const auto& out = pattern.out;
  const auto calib_out = r.count("calib-out") ? pattern.calib_out : out / "calib.mat";
  const int level = pattern.level;
  std::vector<CollectItem> items;
  for (auto& p : calibration_patterns(camera.scene_size, level))
    items.push_back({p.name + ".png", [img = p.image] { return img; }});
  const auto claim = claim_out(r, out, "capture-calibration");
  auto session = open_collection(r, camera);
  const auto rep = collect(items, *session.source, *session.display, collect_options<PatternCollect>(r),
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

CommandFlags cameras_command_flags() { return command_flags("cameras", cameras_flags()); }
CommandFlags capture_command_flags() { return command_flags("capture", capture_flags(), device_flags()); }
CommandFlags capture_dataset_command_flags() {
  return command_flags("capture-dataset", capture_dataset_flags(), collect_flags<PhotoCollect>(), device_flags(),
                       display_flags());
}
CommandFlags capture_calibration_command_flags() {
  return command_flags("capture-calibration", pattern_flags(), collect_flags<PatternCollect>(), device_flags(),
                       display_flags());
}
CommandFlags live_command_flags() { return command_flags("live", live_flags(), device_flags()); }

int live(int argc, char** argv) {
  cxxopts::Options o("flatnet live", "Live view: grab, reconstruct (Tikhonov or FlatNet), show with the frame rate.");
  add_flags(o, live_flags());
  add_precision(o);
  add_camera_flags(o);
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(!(r.count("model") && r.count("calib")), "live", "give --model or --calib, not both");
  LiveSettings set;
  read_flags(r, live_flags(), set);
  ReconstructorSpec spec;
  spec.method = r.count("model") ? "flatnet" : "tikhonov";
  spec.use_camera = !r.count("model") || r.count("camera");  // a model preprocesses as it was trained
  if (spec.use_camera) spec.camera = camera_from(r);
  if (r.count("model")) spec.model = set.model;
  if (r.count("calib")) spec.calibration = set.calib;
  spec.lambda = set.lambda;
  spec.levers.bf16 = r.count("model") && precision_from(r) == Precision::bf16;
  auto built = make_reconstructor(spec);
  const auto& camera = built.camera;
  auto source = open_from_flags(r, camera);
  std::unique_ptr<Display> display;
  if (!set.no_window) {
    DisplayOptions d;
    d.fullscreen = false;
    d.title = "flatnet live";
    d.scale = set.scale;
    display = make_display(d);
  }
  LiveOptions opt;
  opt.geometry = camera.raw;
  opt.frames = set.frames;
  opt.seconds = set.seconds;
  opt.log = display ? nullptr : &std::cout;
  opt.fit = built.fit.get();
  opt.warn = &std::cerr;
  opt.require_fit = set.require_fit;
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
