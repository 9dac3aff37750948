#include "hw/capture.hpp"

#include <ctime>
#include <iomanip>
#include <limits>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"

namespace flatnet {

namespace {

std::string utc_now() {
  const std::time_t t = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&t, &tm);
  std::ostringstream s;
  s << std::put_time(&tm, "%Y-%m-%dT%H:%M:%SZ");
  return s.str();
}

// The next free index: one past the highest PREFIX_NNNN.png already in the folder.
int64_t next_index(const std::filesystem::path& dir, const std::string& prefix) {
  int64_t next = 0;
  if (!std::filesystem::exists(dir)) return 0;
  for (const auto& e : std::filesystem::directory_iterator(dir)) {
    const auto stem = e.path().stem().string();
    if (e.path().extension() != ".png" || stem.rfind(prefix + "_", 0) != 0) continue;
    try {
      const int64_t index = std::stoll(stem.substr(prefix.size() + 1));
      if (index < std::numeric_limits<int64_t>::max()) next = std::max<int64_t>(next, index + 1);
    } catch (const std::exception&) {
    }
  }
  return next;
}

}  // namespace

torch::Tensor average_frames(FrameSource& source, int k, FrameSource::Clock::time_point not_before,
                             std::vector<uint64_t>* ids) {
  require_option(k >= 1, "capture.average", "must be at least 1");
  torch::Tensor sum;
  for (int i = 0; i < k; ++i) {
    const auto frame = source.next_frame(not_before);
    // Exact: integer sums of <= 16-bit codes cannot overflow int64.
    sum = sum.defined() ? sum + frame.codes.to(torch::kInt64) : frame.codes.to(torch::kInt64);
    if (ids) ids->push_back(frame.frame_id);
  }
  return sum.to(torch::kFloat64) / k;
}

nlohmann::json capture_sidecar(const FrameSource& source, int average, const std::vector<uint64_t>& ids) {
  auto j = source.describe();
  j["frames_averaged"] = average;
  j["frame_ids"] = ids;
  j["captured_utc"] = utc_now();
  j["stored_as"] = "16-bit PNG of the sensor mosaic; stored = round(mean code * 2^(16 - adc_bits))";
  j["stored_scale"] = 1 << (16 - source.format().bits);
  j["flatnet_version"] = FLATNET_VERSION;
  return j;
}

void write_raw_capture(const std::filesystem::path& png, const torch::Tensor& mean_codes, const PixelFormatInfo& format,
                       const nlohmann::json& sidecar) {
  if (!png.parent_path().empty()) std::filesystem::create_directories(png.parent_path());
  auto json_path = png;
  json_path.replace_extension(".json");
  write_text_atomically(json_path, sidecar.dump(2) + "\n");
  write_gray16(png, codes_to_stored(mean_codes, format.bits));
}

CaptureReport capture_frames(FrameSource& source, const CaptureOptions& opt) {
  require_option(opt.frames >= 1, "capture.frames", "must be at least 1");
  std::filesystem::create_directories(opt.out);
  CaptureReport rep;
  rep.first_index = next_index(opt.out, opt.prefix);
  Progress progress("capture", opt.frames, opt.progress);
  const auto start = std::chrono::steady_clock::now();
  const FinishItemOnInterrupt finish_frame;  // Ctrl-C ends this frame, then the loop
  for (int i = 0; i < opt.frames && !interrupted(); ++i) {
    std::vector<uint64_t> ids;
    const auto mean = average_frames(source, opt.average, FrameSource::Clock::now(), &ids);
    std::ostringstream name;
    name << opt.prefix << "_" << std::setw(4) << std::setfill('0') << rep.first_index + i << ".png";
    write_raw_capture(opt.out / name.str(), mean, source.format(), capture_sidecar(source, opt.average, ids));
    ++rep.written;
    progress.tick();
  }
  progress.finish();
  rep.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  rep.frames_per_s = rep.written * opt.average / std::max(rep.seconds, 1e-9);
  return rep;
}

}  // namespace flatnet
