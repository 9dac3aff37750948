#include "eval/plot.hpp"

#include <opencv2/imgproc.hpp>

#include "core/error.hpp"
#include "io/image.hpp"

namespace flatnet {

void write_line_plot(const std::filesystem::path& path, const std::vector<Series>& series, const PlotOptions& o) {
  cv::Mat img(o.height, o.width, CV_8UC3, cv::Scalar(255, 255, 255));
  const int left = 70, right = 160, top = 36, bottom = 50;
  const int pw = o.width - left - right, ph = o.height - top - bottom;
  auto tx = [&](double x) { return o.log_x ? std::log10(std::max(x, 1e-300)) : x; };
  double x0 = 1e300, x1 = -1e300, y0 = 1e300, y1 = -1e300;
  for (const auto& s : series)
    for (size_t i = 0; i < s.x.size(); ++i) {
      if (!std::isfinite(s.y[i])) continue;
      x0 = std::min(x0, tx(s.x[i]));
      x1 = std::max(x1, tx(s.x[i]));
      y0 = std::min(y0, s.y[i]);
      y1 = std::max(y1, s.y[i]);
    }
  if (x0 > x1) x0 = 0, x1 = 1, y0 = 0, y1 = 1;
  if (x1 == x0) x1 = x0 + 1;
  if (y1 == y0) y1 = y0 + 1;
  const double pad = 0.05 * (y1 - y0);
  y0 -= pad, y1 += pad;
  auto px = [&](double x) { return left + static_cast<int>((tx(x) - x0) / (x1 - x0) * pw); };
  auto py = [&](double y) { return top + ph - static_cast<int>((y - y0) / (y1 - y0) * ph); };
  const auto black = cv::Scalar(0, 0, 0), grey = cv::Scalar(220, 220, 220);
  for (int k = 0; k <= 4; ++k) {  // grid and tick labels
    const double yv = y0 + k * (y1 - y0) / 4, xv = x0 + k * (x1 - x0) / 4;
    const int yy = top + ph - k * ph / 4, xx = left + k * pw / 4;
    cv::line(img, {left, yy}, {left + pw, yy}, grey);
    cv::line(img, {xx, top}, {xx, top + ph}, grey);
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.3g", yv);
    cv::putText(img, buf, {5, yy + 4}, cv::FONT_HERSHEY_SIMPLEX, 0.4, black, 1, cv::LINE_AA);
    std::snprintf(buf, sizeof buf, "%.3g", o.log_x ? std::pow(10.0, xv) : xv);
    cv::putText(img, buf, {xx - 15, top + ph + 18}, cv::FONT_HERSHEY_SIMPLEX, 0.4, black, 1, cv::LINE_AA);
  }
  cv::rectangle(img, {left, top}, {left + pw, top + ph}, black);
  const std::vector<cv::Scalar> colours = {{200, 80, 0},   {0, 120, 230}, {40, 160, 40}, {30, 30, 200},
                                           {150, 50, 150}, {0, 170, 170}, {90, 90, 90}};
  for (size_t s = 0; s < series.size(); ++s) {
    const auto& c = colours[s % colours.size()];
    std::vector<cv::Point> pts;
    for (size_t i = 0; i < series[s].x.size(); ++i)
      if (std::isfinite(series[s].y[i])) pts.emplace_back(px(series[s].x[i]), py(series[s].y[i]));
    if (pts.size() > 1) cv::polylines(img, pts, false, c, 2, cv::LINE_AA);
    for (const auto& p : pts) cv::circle(img, p, 3, c, -1, cv::LINE_AA);
    cv::line(img, {left + pw + 10, top + 12 + 20 * static_cast<int>(s)},
             {left + pw + 30, top + 12 + 20 * static_cast<int>(s)}, c, 2);
    cv::putText(img, series[s].name.substr(0, 18), {left + pw + 35, top + 16 + 20 * static_cast<int>(s)},
                cv::FONT_HERSHEY_SIMPLEX, 0.42, black, 1, cv::LINE_AA);
  }
  cv::putText(img, o.title, {left, 24}, cv::FONT_HERSHEY_SIMPLEX, 0.55, black, 1, cv::LINE_AA);
  cv::putText(img, o.xlabel, {left + pw / 2 - 40, o.height - 10}, cv::FONT_HERSHEY_SIMPLEX, 0.45, black, 1,
              cv::LINE_AA);
  cv::putText(img, o.ylabel, {5, top - 10}, cv::FONT_HERSHEY_SIMPLEX, 0.45, black, 1, cv::LINE_AA);
  // OpenCV draws BGR; the image writer takes RGB {3,H,W} in [0,1].
  auto bgr = torch::from_blob(img.data, {o.height, o.width, 3}, torch::kUInt8);
  write_rgb8(path, bgr.flip({2}).permute({2, 0, 1}).to(torch::kFloat32) / 255.0f);
}

}  // namespace flatnet
