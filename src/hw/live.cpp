#include "hw/live.hpp"

#include <algorithm>
#include <deque>
#include <iomanip>
#include <ostream>
#include <sstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "hw/capture.hpp"
#include "io/raw.hpp"

namespace flatnet {

namespace {
using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t) { return std::chrono::duration<double, std::milli>(Clock::now() - t).count(); }

// One frame's camera fit, counted in `s`; the text the overlay shows. The first misfit is said on
// opt.warn, or ends the view under require_fit.
// `recent`: the last kFitWindow judged frames' results, judged as a batch too (judge_batch).
std::string judge_frame(const CameraFit& fit, const torch::Tensor& raw_unit, const LiveOptions& opt, LiveStats& s,
                        std::deque<CameraFitResult>& recent) {
  const auto result = fit.measure(raw_unit);
  ++s.fit_checks;
  if (result.judged) recent.push_back(result);
  if (recent.size() > kFitWindow) recent.pop_front();
  const auto stream = judge_batch(fit, {recent.begin(), recent.end()});
  std::ostringstream text;
  text << std::fixed << std::setprecision(2);
  if (result.matches && !stream.foreign) {
    if (!result.judged) return "camera fit: not judged (saturated)";
    text << "camera fit " << result.fit;
    return text.str();
  }
  ++s.misfits;
  if (result.judged) s.worst_fit = std::max(s.worst_fit, result.fit);
  std::ostringstream line;
  line << std::setprecision(3) << "frame " << s.frames + 1 << " does not fit camera '" << printable(fit.camera_name())
       << "' (";
  if (stream.foreign)
    line << "with the last " << stream.judged << " judged frames: their median is " << stream.median_excess
         << "x the camera fit's thresholds; this frame: ";
  line << fit.verdict(result) << "): " << misfit_advice();
  require_option(!opt.require_fit, "live.require_fit", line.str());
  if (s.misfits == 1 && opt.warn) *opt.warn << "warning: live: " << line.str() << std::endl;
  text << "NOT camera '" << printable(fit.camera_name()) << "' (";
  if (result.matches)
    text << "frames' median " << stream.median_excess << "x";
  else
    text << (result.leak_matches ? "fit " : "leak ") << (result.leak_matches ? result.fit : result.leak);
  text << ")";
  return text.str();
}
}  // namespace

LiveStats run_live(FrameSource& source, Reconstructor& engine, Display* display, const LiveOptions& opt) {
  c10::InferenceMode inference;
  LiveStats s;
  double grab = 0, prep = 0, recon = 0, show = 0;
  const auto start = Clock::now();
  auto last_report = start;
  int64_t frames_at_report = 0;
  std::string overlay, fit_text;
  std::deque<CameraFitResult> recent_fits;  // the stream's last judged frames
  auto last_fit = start;
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
                  std::to_string(opt.geometry.raw_height) + " (set " + option_key("live.region") +
                  " or use the matching camera .yaml)");
    }
    t = Clock::now();
    const auto unit = codes_to_unit(frame.codes, source.format().bits);
    const auto planes = preprocess_raw(unit, opt.geometry);
    prep += ms_since(t);
    if (opt.fit &&
        (s.frames == 0 || std::chrono::duration<double>(Clock::now() - last_fit).count() >= opt.fit_seconds)) {
      fit_text = judge_frame(*opt.fit, unit, opt, s, recent_fits);
      last_fit = Clock::now();
    }
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
      if (!fit_text.empty()) text << ", " << fit_text;
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
