#include "hw/display.hpp"

#include <cstdlib>
#include <thread>

#include <opencv2/highgui.hpp>
#include <opencv2/imgproc.hpp>

#include "core/error.hpp"

namespace flatnet {

torch::Tensor compose_canvas(const torch::Tensor& image, int64_t canvas_h, int64_t canvas_w, int scale) {
  auto img = image.dim() == 2 ? image.unsqueeze(0).expand({3, -1, -1}) : image;
  require(img.dim() == 3 && img.size(0) == 3, "display", "expects a {3,H,W} or {H,W} image");
  const int64_t h = img.size(1), w = img.size(2);
  if (scale <= 0) scale = static_cast<int>(std::max<int64_t>(1, std::min(canvas_h / h, canvas_w / w)));
  auto u8 = torch::round(img.clamp(0, 1) * 255).to(torch::kUInt8).flip(0).permute({1, 2, 0});  // RGB -> BGR, HWC
  if (scale > 1) u8 = u8.repeat_interleave(scale, 0).repeat_interleave(scale, 1);
  canvas_h = std::max(canvas_h, u8.size(0));
  canvas_w = std::max(canvas_w, u8.size(1));
  auto canvas = torch::zeros({canvas_h, canvas_w, 3}, torch::kUInt8);
  const int64_t top = (canvas_h - u8.size(0)) / 2, left = (canvas_w - u8.size(1)) / 2;
  canvas.slice(0, top, top + u8.size(0)).slice(1, left, left + u8.size(1)).copy_(u8);
  return canvas;
}

namespace {

class HeadlessDisplay final : public Display {
 public:
  void show(const torch::Tensor&, const std::string&) override { ++shown_; }
  bool wait(int ms) override {  // stands in for the settle time a real display needs
    std::this_thread::sleep_for(std::chrono::milliseconds(ms));
    return false;
  }
  int64_t shown() const override { return shown_; }

 private:
  int64_t shown_ = 0;
};

class WindowDisplay final : public Display {
 public:
  explicit WindowDisplay(DisplayOptions o) : opt_(std::move(o)) {
    const char* x11 = std::getenv("DISPLAY");
    const char* wayland = std::getenv("WAYLAND_DISPLAY");
    require((x11 && *x11) || (wayland && *wayland), "display",
            "no display server (DISPLAY is not set); run under a desktop session, xvfb-run, or use --display none / "
            "--no-window");
    cv::namedWindow(opt_.title, opt_.fullscreen ? cv::WINDOW_NORMAL : cv::WINDOW_AUTOSIZE);
    cv::moveWindow(opt_.title, opt_.x, opt_.y);
    if (opt_.fullscreen) cv::setWindowProperty(opt_.title, cv::WND_PROP_FULLSCREEN, cv::WINDOW_FULLSCREEN);
    cv::waitKey(1);
  }
  ~WindowDisplay() override { cv::destroyWindow(opt_.title); }

  void show(const torch::Tensor& image, const std::string& text) override {
    int64_t h = 0, w = 0;
    if (opt_.fullscreen) {
      const auto rect = cv::getWindowImageRect(opt_.title);
      h = std::max(rect.height, 1);
      w = std::max(rect.width, 1);
    }
    auto canvas = compose_canvas(image, h, w, opt_.fullscreen ? opt_.scale : std::max(1, opt_.scale)).contiguous();
    cv::Mat mat(static_cast<int>(canvas.size(0)), static_cast<int>(canvas.size(1)), CV_8UC3,
                canvas.data_ptr<uint8_t>());
    if (!text.empty()) cv::putText(mat, text, {10, 30}, cv::FONT_HERSHEY_SIMPLEX, 0.8, {0, 255, 0}, 2);
    cv::imshow(opt_.title, mat);
    ++shown_;
  }

  bool wait(int ms) override {
    const int key = cv::waitKey(std::max(1, ms));
    return key == 27 || key == 'q';
  }
  int64_t shown() const override { return shown_; }

 private:
  DisplayOptions opt_;
  int64_t shown_ = 0;
};

}  // namespace

std::unique_ptr<Display> make_display(const DisplayOptions& options) {
  if (options.kind == "none") return std::make_unique<HeadlessDisplay>();
  require_option(options.kind == "window", "collect.display", "expected window or none, got '" + options.kind + "'");
  return std::make_unique<WindowDisplay>(options);
}

}  // namespace flatnet
