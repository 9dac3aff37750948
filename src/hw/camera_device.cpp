#include "hw/camera_device.hpp"

#include <atomic>
#include <iostream>
#include <thread>

#include "core/error.hpp"

#ifdef FLATNET_WITH_ARAVIS
#include <arv.h>
#endif

namespace flatnet {

namespace {
constexpr const char* kFakeId = "Fake_1";
}

std::string resolve_device_id(const std::string& id) {
  std::string lower = id;
  std::transform(lower.begin(), lower.end(), lower.begin(), ::tolower);
  return lower == "fake" ? kFakeId : id;
}

#ifndef FLATNET_WITH_ARAVIS

bool have_aravis() { return false; }
std::vector<DeviceInfo> list_cameras(bool) {
  throw Error("this flatnet was built without Aravis (cmake -DFLATNET_WITH_ARAVIS=ON needs libaravis-dev)");
}
std::unique_ptr<FrameSource> open_camera(const std::string& id, const DeviceSettings&) {
  throw Error("camera " + id + ": this flatnet was built without Aravis (cmake -DFLATNET_WITH_ARAVIS=ON)");
}

#else

bool have_aravis() { return true; }

namespace {

std::string str(const char* s) { return s ? s : ""; }

// Throws an Error naming the device and the operation when a GError was set.
void check(GError*& err, const std::string& device, const std::string& what) {
  if (!err) return;
  const std::string msg = err->message;
  g_clear_error(&err);
  throw Error("camera " + device + ": " + what + ": " + msg);
}

const char* buffer_status_name(ArvBufferStatus s) {
  switch (s) {
    case ARV_BUFFER_STATUS_SUCCESS:
      return "success";
    case ARV_BUFFER_STATUS_CLEARED:
      return "buffer cleared";
    case ARV_BUFFER_STATUS_TIMEOUT:
      return "incomplete buffer (timeout before all packets arrived)";
    case ARV_BUFFER_STATUS_MISSING_PACKETS:
      return "incomplete buffer (missing packets)";
    case ARV_BUFFER_STATUS_WRONG_PACKET_ID:
      return "corrupt buffer (wrong packet id)";
    case ARV_BUFFER_STATUS_SIZE_MISMATCH:
      return "image larger than the buffer (size mismatch)";
    case ARV_BUFFER_STATUS_FILLING:
      return "buffer still filling";
    case ARV_BUFFER_STATUS_ABORTED:
      return "acquisition aborted";
    default:
      return "unknown buffer status";
  }
}

void enable_fake_if_needed(const std::string& id) {
  if (id.rfind("Fake", 0) == 0) arv_enable_interface("Fake");
}

class AravisCamera final : public FrameSource {
 public:
  AravisCamera(std::string id, DeviceSettings settings) : id_(std::move(id)), settings_(std::move(settings)) { open(); }
  ~AravisCamera() override { close(); }

  Frame next_frame(Clock::time_point not_before) override {
    std::string last_failure;
    for (int attempt = 0; attempt <= settings_.retries; ++attempt) {
      try {
        if (attempt > 0) recover(attempt, last_failure);
        if (auto frame = pop_frame(not_before, last_failure)) return *frame;
      } catch (const Error& e) {  // reopening failed: counts as a failed attempt
        last_failure = e.what();
      }
    }
    throw Error("camera " + id_ + ": no complete frame after " + std::to_string(settings_.retries + 1) +
                " attempts (last: " + last_failure + "); check the connection, that " +
                option_key("capture.timeout_ms") +
                " exceeds the exposure, "
                "and for GigE Vision the packet size");
  }

  Frame latest_frame() override {
    Frame frame = next_frame(Clock::time_point{});
    // Drain the backlog: keep only the newest complete buffer.
    while (ArvBuffer* b = arv_stream_try_pop_buffer(stream_)) {
      if (arv_buffer_get_status(b) == ARV_BUFFER_STATUS_SUCCESS) {
        try {
          frame = to_frame(b);
        } catch (const Error&) {
        }
      }
      arv_stream_push_buffer(stream_, b);
    }
    return frame;
  }

  const PixelFormatInfo& format() const override { return format_; }
  nlohmann::json describe() const override { return description_; }
  int64_t recovered_failures() const override { return failures_; }

 private:
  static void on_control_lost(ArvDevice*, gpointer self) { static_cast<AravisCamera*>(self)->control_lost_ = true; }

  void open() {
    enable_fake_if_needed(id_);
    GError* err = nullptr;
    camera_ = arv_camera_new(id_.c_str(), &err);
    if (!camera_ || err) {
      const std::string msg = err ? err->message : "not found";
      g_clear_error(&err);
      throw Error("camera " + id_ + ": cannot open (" + msg + "); 'flatnet cameras' lists the connected ones");
    }
    g_signal_connect(arv_camera_get_device(camera_), "control-lost", G_CALLBACK(on_control_lost), this);
    control_lost_ = false;
    apply_settings();
    start_stream();
    describe_device();
  }

  void close() {
    if (camera_) {
      GError* err = nullptr;
      arv_camera_stop_acquisition(camera_, &err);
      g_clear_error(&err);
    }
    if (stream_) g_object_unref(stream_), stream_ = nullptr;
    if (camera_) g_object_unref(camera_), camera_ = nullptr;
  }

  void apply_settings() {
    GError* err = nullptr;
    const auto& s = settings_;
    if (!s.pixel_format.empty()) {
      describe_pixel_format(s.pixel_format);  // refuse unstorable formats before touching the camera
      guint n = 0;
      const char** available = arv_camera_dup_available_pixel_formats_as_strings(camera_, &n, &err);
      check(err, id_, "reading the pixel formats");
      std::vector<std::string> names(available, available + n);
      g_free(available);
      if (std::find(names.begin(), names.end(), s.pixel_format) == names.end()) {
        std::string list;
        for (const auto& name : names)
          list += (list.empty() ? "" : ", ") + name + (is_storable_pixel_format(name) ? "" : " (not storable)");
        throw Error("camera " + id_ + ": pixel format " + s.pixel_format + " not offered; it offers " + list);
      }
      arv_camera_set_pixel_format_from_string(camera_, s.pixel_format.c_str(), &err);
      check(err, id_, "setting PixelFormat=" + s.pixel_format);
    }
    format_ = describe_pixel_format(str(arv_camera_get_pixel_format_as_string(camera_, &err)));
    check(err, id_, "reading PixelFormat");
    if (s.region) {
      const auto [x, y, w, h] = *s.region;
      gint wmin = 0, wmax = 0, hmin = 0, hmax = 0;
      arv_camera_get_width_bounds(camera_, &wmin, &wmax, &err);
      arv_camera_get_height_bounds(camera_, &hmin, &hmax, &err);
      check(err, id_, "reading the sensor size");
      require(x + w <= wmax && y + h <= hmax, "camera " + id_,
              "region " + std::to_string(w) + "x" + std::to_string(h) + "+" + std::to_string(x) + "+" +
                  std::to_string(y) + " exceeds the sensor's " + std::to_string(wmax) + "x" + std::to_string(hmax));
      arv_camera_set_region(camera_, static_cast<gint>(x), static_cast<gint>(y), static_cast<gint>(w),
                            static_cast<gint>(h), &err);
      check(err, id_, "setting the region");
    }
    // Exposure and gain: automatic control off, the value checked against the camera's bounds.
    auto set_bounded = [&](const char* what, const char* unit, double value, auto bounds, auto set) {
      double lo = 0, hi = 0;
      bounds(camera_, &lo, &hi, &err);
      check(err, id_, std::string("reading the ") + what + " bounds");
      require(value >= lo && value <= hi, "camera " + id_,
              std::string(what) + " " + std::to_string(value) + " " + unit + " outside [" + std::to_string(lo) + ", " +
                  std::to_string(hi) + "]");
      set(camera_, value, &err);
      check(err, id_, std::string("setting the ") + what);
    };
    if (s.exposure_us) {
      if (arv_camera_is_exposure_auto_available(camera_, nullptr))
        arv_camera_set_exposure_time_auto(camera_, ARV_AUTO_OFF, nullptr);
      set_bounded("exposure", "us", *s.exposure_us, arv_camera_get_exposure_time_bounds, arv_camera_set_exposure_time);
    }
    if (s.gain_db) {
      if (arv_camera_is_gain_auto_available(camera_, nullptr)) arv_camera_set_gain_auto(camera_, ARV_AUTO_OFF, nullptr);
      set_bounded("gain", "dB", *s.gain_db, arv_camera_get_gain_bounds, arv_camera_set_gain);
    }
    if (s.frame_rate) {
      arv_camera_set_frame_rate(camera_, *s.frame_rate, &err);
      check(err, id_, "setting AcquisitionFrameRate");
    }
    if (arv_camera_is_gv_device(camera_)) {
      if (s.packet_size > 0)
        arv_camera_gv_set_packet_size(camera_, static_cast<gint>(s.packet_size), &err);
      else
        arv_camera_gv_auto_packet_size(camera_, &err);
      check(err, id_, "setting the GigE Vision packet size");
    }
  }

  void start_stream() {
    GError* err = nullptr;
    arv_camera_set_acquisition_mode(camera_, ARV_ACQUISITION_MODE_CONTINUOUS, &err);
    check(err, id_, "setting AcquisitionMode=Continuous");
    payload_ = arv_camera_get_payload(camera_, &err);
    check(err, id_, "reading the payload size");
    stream_ = arv_camera_create_stream(camera_, nullptr, nullptr, &err);
    check(err, id_, "creating the stream");
    for (int i = 0; i < std::max(2, settings_.buffers); ++i)
      arv_stream_push_buffer(stream_, arv_buffer_new(payload_, nullptr));
    arv_camera_start_acquisition(camera_, &err);
    check(err, id_, "starting the acquisition");
  }

  void describe_device() {
    GError* err = nullptr;
    gint x = 0, y = 0, w = 0, h = 0;
    arv_camera_get_region(camera_, &x, &y, &w, &h, &err);
    check(err, id_, "reading the region");
    width_ = w;
    height_ = h;
    nlohmann::json d;
    d["device"] = id_;
    d["vendor"] = str(arv_camera_get_vendor_name(camera_, nullptr));
    d["model"] = str(arv_camera_get_model_name(camera_, nullptr));
    d["serial"] = str(arv_camera_get_device_serial_number(camera_, nullptr));
    d["protocol"] = arv_camera_is_gv_device(camera_)   ? "GigEVision"
                    : arv_camera_is_uv_device(camera_) ? "USB3Vision"
                    : id_.rfind("Fake", 0) == 0        ? "Fake"
                                                       : "other";
    d["pixel_format"] = format_.name;
    d["adc_bits"] = format_.bits;
    d["bayer"] = format_.bayer.empty() ? "none" : format_.bayer;
    d["region"] = {{"x", x}, {"y", y}, {"width", w}, {"height", h}};
    if (arv_camera_is_exposure_time_available(camera_, nullptr))
      d["exposure_us"] = arv_camera_get_exposure_time(camera_, nullptr);
    if (arv_camera_is_gain_available(camera_, nullptr)) d["gain_db"] = arv_camera_get_gain(camera_, nullptr);
    if (arv_camera_is_frame_rate_available(camera_, nullptr))
      d["frame_rate"] = arv_camera_get_frame_rate(camera_, nullptr);
    if (arv_camera_is_gv_device(camera_)) d["packet_size"] = arv_camera_gv_get_packet_size(camera_, nullptr);
    description_ = d;
  }

  // Unpacks a successful buffer, checking it is the image the camera was set up for.
  Frame to_frame(ArvBuffer* b) {
    const int w = arv_buffer_get_image_width(b), h = arv_buffer_get_image_height(b);
    require(w == width_ && h == height_, "camera " + id_,
            "frame is " + std::to_string(w) + "x" + std::to_string(h) + ", expected " + std::to_string(width_) + "x" +
                std::to_string(height_));
    size_t size = 0;
    const auto* data = static_cast<const uint8_t*>(arv_buffer_get_data(b, &size));
    Frame f;
    f.codes = unpack_frame(data, size, w, h, format_);
    f.frame_id = arv_buffer_get_frame_id(b);
    f.timestamp_ns = static_cast<int64_t>(arv_buffer_get_system_timestamp(b));
    return f;
  }

  // One attempt: a complete frame newer than not_before, or nullopt with the reason in `failure`.
  std::optional<Frame> pop_frame(Clock::time_point not_before, std::string& failure) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(settings_.timeout_ms);
    const int64_t not_before_ns =
        std::chrono::duration_cast<std::chrono::nanoseconds>(not_before.time_since_epoch()).count();
    while (true) {
      const auto left =
          std::chrono::duration_cast<std::chrono::microseconds>(deadline - std::chrono::steady_clock::now()).count();
      if (left <= 0 || control_lost_) {
        failure = control_lost_ ? "connection lost" : "no frame within " + std::to_string(settings_.timeout_ms) + " ms";
        return std::nullopt;
      }
      ArvBuffer* b = arv_stream_timeout_pop_buffer(stream_, static_cast<guint64>(left));
      if (!b) continue;  // timed out: the loop reports it
      std::optional<Frame> frame;
      std::string why;
      const auto status = arv_buffer_get_status(b);
      if (status != ARV_BUFFER_STATUS_SUCCESS) {
        why = buffer_status_name(status);
      } else if (static_cast<int64_t>(arv_buffer_get_system_timestamp(b)) >= not_before_ns) {
        try {
          frame = to_frame(b);
        } catch (const Error& e) {
          why = e.what();
        }
      }                                    // else: exposed before not_before, dropped
      arv_stream_push_buffer(stream_, b);  // back to the driver, whatever it held
      if (frame) return frame;
      if (!why.empty()) {
        failure = why;
        return std::nullopt;
      }
    }
  }

  // Reports a failed attempt; reconnects when the camera stopped answering.
  void recover(int attempt, const std::string& failure) {
    ++failures_;
    std::cerr << "camera " << id_ << ": " << failure << " (retry " << attempt << "/" << settings_.retries << ")\n";
    const bool reconnect = control_lost_ || failure.rfind("no frame", 0) == 0;
    if (!reconnect) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(200 * attempt));
    close();
    open();  // throws if the camera is still gone; the caller counts it as a failed attempt
    std::cerr << "camera " << id_ << ": reconnected\n";
  }

  std::string id_;
  DeviceSettings settings_;
  ArvCamera* camera_ = nullptr;
  ArvStream* stream_ = nullptr;
  guint payload_ = 0;
  int width_ = 0, height_ = 0;
  PixelFormatInfo format_;
  nlohmann::json description_;
  std::atomic<bool> control_lost_{false};
  int64_t failures_ = 0;
};

}  // namespace

std::vector<DeviceInfo> list_cameras(bool include_fake) {
  if (include_fake) arv_enable_interface("Fake");
  arv_update_device_list();
  std::vector<DeviceInfo> out;
  for (unsigned i = 0; i < arv_get_n_devices(); ++i)
    out.push_back({str(arv_get_device_id(i)), str(arv_get_device_vendor(i)), str(arv_get_device_model(i)),
                   str(arv_get_device_serial_nbr(i)), str(arv_get_device_protocol(i)), str(arv_get_device_address(i))});
  return out;
}

std::unique_ptr<FrameSource> open_camera(const std::string& id, const DeviceSettings& settings) {
  // A camera just plugged in (or restarting) may not answer yet: retry opening a few times.
  for (int attempt = 0;; ++attempt) {
    try {
      return std::make_unique<AravisCamera>(resolve_device_id(id), settings);
    } catch (const Error& e) {
      if (attempt >= settings.retries || std::string(e.what()).find("cannot open") == std::string::npos) throw;
      std::this_thread::sleep_for(std::chrono::milliseconds(300 * (attempt + 1)));
    }
  }
}

#endif

}  // namespace flatnet
