#include "hw/live.hpp"

#include <iomanip>
#include <ostream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "hw/capture.hpp"
#include "io/raw.hpp"

namespace flatnet {

namespace {
using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t) { return std::chrono::duration<double, std::milli>(Clock::now() - t).count(); }
}  // namespace

LiveStats run_live(FrameSource& source, Reconstructor& engine, Display* display, const LiveOptions& opt) {
  c10::InferenceMode inference;
  LiveStats s;
  double grab = 0, prep = 0, recon = 0, show = 0;
  const auto start = Clock::now();
  auto last_report = start;
  int64_t frames_at_report = 0;
  std::string overlay;
  const FinishItemOnInterrupt finish_frame;  // Ctrl-C ends this frame, then the loop
  while (!interrupted()) {
    if (opt.frames > 0 && s.frames >= opt.frames) break;
    if (opt.seconds > 0 && std::chrono::duration<double>(Clock::now() - start).count() >= opt.seconds) break;
    auto t = Clock::now();
    const auto frame = source.latest_frame();
    grab += ms_since(t);
    if (s.frames == 0) {
      require(frame.codes.size(0) == opt.geometry.raw_height && frame.codes.size(1) == opt.geometry.raw_width, "camera",
              "frames are " + std::to_string(frame.codes.size(1)) + "x" + std::to_string(frame.codes.size(0)) +
                  " but the camera file expects " + std::to_string(opt.geometry.raw_width) + "x" +
                  std::to_string(opt.geometry.raw_height) + " (set live.region or use the matching camera .yaml)");
    }
    t = Clock::now();
    const auto planes = preprocess_raw(codes_to_unit(frame.codes, source.format().bits), opt.geometry);
    prep += ms_since(t);
    t = Clock::now();
    const auto image = engine.reconstruct(planes.unsqueeze(0))[0];  // {4,h,w} -> {3,N,N}
    recon += ms_since(t);
    ++s.frames;
    t = Clock::now();
    if (display) {
      display->show(image, overlay);
      if (display->wait(1)) break;
    }
    show += ms_since(t);
    const double since = std::chrono::duration<double>(Clock::now() - last_report).count();
    if (since >= 1.0) {
      std::ostringstream text;
      text << std::fixed << std::setprecision(1) << (s.frames - frames_at_report) / since << " fps (reconstruct "
           << recon / s.frames << " ms)";
      overlay = text.str();
      if (opt.log) *opt.log << "live: " << overlay << std::endl;
      last_report = Clock::now();
      frames_at_report = s.frames;
    }
  }
  const double total = std::chrono::duration<double>(Clock::now() - start).count();
  if (s.frames > 0) {
    s.fps = s.frames / total;
    s.grab_ms = grab / s.frames, s.preprocess_ms = prep / s.frames, s.reconstruct_ms = recon / s.frames,
    s.show_ms = show / s.frames;
  }
  return s;
}

}  // namespace flatnet
