#pragma once
// Minimal line plots (training curves, noise sweeps) as PNG, drawn with OpenCV.
#include <filesystem>
#include <string>
#include <vector>

namespace flatnet {

struct Series {
  std::string name;
  std::vector<double> x, y;
};

struct PlotOptions {
  std::string title, xlabel, ylabel;
  bool log_x = false;
  int width = 720, height = 440;
};

void write_line_plot(const std::filesystem::path& path, const std::vector<Series>& series, const PlotOptions& options);

}  // namespace flatnet
