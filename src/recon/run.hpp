#pragma once
// Reconstructing folders of raw captures with a classical method.
#include <filesystem>
#include <string>
#include <vector>

#include "core/camera_config.hpp"
#include "optics/camera.hpp"

namespace flatnet {

struct ReconOptions {
  std::string method = "tikhonov";  // tikhonov | tv
  double lambda = 0;                // <= 0: the camera file's default for the method
  std::filesystem::path out;
  int batch = 8;
  bool progress = true;
};

struct ReconReport {
  int64_t count = 0;
  double recon_ms_per_capture = 0;  // reconstruction alone (no file I/O)
  double seconds = 0;               // everything, I/O included
};

// A FILE, every .png in a DIR (sorted), files matching a pattern (DIR/fc_*.png), or the files a
// .txt list names (relative to the list's folder).
std::vector<std::filesystem::path> collect_captures(const std::filesystem::path& input);
// Each capture's reconstruction is written to OUT/<capture name>.png. Throws (naming the files)
// when two captures would write one output, or an output would replace a capture being read
// (--out equal to the input folder).
void check_output_names(const std::vector<std::filesystem::path>& captures, const std::filesystem::path& out);

// Linear-light planes {4,N,N} (b, gb, gr, r) -> sRGB image {3,N,N} in [0,1].
torch::Tensor planes_to_srgb(const torch::Tensor& planes);

ReconReport reconstruct_files(const CameraConfig& camera, const Calibration& calib,
                              const std::vector<std::filesystem::path>& captures, const ReconOptions& options);

}  // namespace flatnet
