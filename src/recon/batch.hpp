#pragma once
// Reconstructing files: raw captures -> the engine's preprocessing -> any Reconstructor -> sRGB
// PNGs with the captures' names. The one batch loop of `flatnet recon`, `infer`, `demo` and `report`.
#include <filesystem>
#include <vector>

#include "io/camera_config.hpp"
#include "optics/camera_fit.hpp"
#include "recon/reconstructor.hpp"

namespace flatnet {

// A FILE, every .png in a DIR (sorted), files matching a pattern (DIR/fc_*.png), or the files a
// .txt list names (relative to the list's folder).
std::vector<std::filesystem::path> collect_captures(const std::filesystem::path& input);
// Each capture's reconstruction is written to OUT/<capture name>.png. Throws (naming the files)
// when two captures would write one output, or an output would replace a capture being read
// (--out equal to the input folder).
void check_output_names(const std::vector<std::filesystem::path>& captures, const std::filesystem::path& out);

struct BatchOptions {
  std::filesystem::path out;  // created when missing
  int batch = 4;              // captures per reconstruct() call
  bool progress = true;
  std::string label = "recon";  // the progress line's name
  // The camera fit of each capture (optics/camera_fit.hpp), written to OUT/camera_fit.csv; null: none.
  const CameraFit* fit = nullptr;
  bool require_fit = false;  // refuse (before reconstructing anything) when a capture does not fit
};

struct BatchReport {
  int64_t count = 0;
  int64_t misfits = 0;   // captures whose camera fit failed
  int64_t unjudged = 0;  // captures too saturated for the camera fit to judge
  std::string worst;     // the worst-fitting capture's name, and its fit
  double worst_fit = 0;
  std::string worst_verdict;  // why the worst capture does not fit (CameraFit::verdict)
  double worst_excess = 0;    // how far it is from fitting (CameraFit::excess)
  BatchFit batch;             // the batch judged as a whole (optics/camera_fit.hpp judge_batch)
  // The engine alone (no file I/O), in steady state: when there is more than one batch the first is
  // left out, since it also sets the engine up (weights reordered, buffers first touched: seconds
  // for a paper-width model). first_batch_ms is that batch's time per capture.
  double ms_per_capture = 0;
  double first_batch_ms = 0;
  bool steady_state = false;  // ms_per_capture leaves the first batch out (there was more than one)
  double captures_per_s = 0;  // everything, file I/O included
  double seconds = 0;
};

// One line for the user when captures do not fit the camera ("" when all fit): how many, the worst,
// and what to do.
std::string camera_fit_warning(const BatchReport& report, const CameraFit& fit);
// One line when saturated captures were not judged ("" when none).
std::string camera_fit_note(const BatchReport& report);

// `camera` is the preprocessing the engine expects (BuiltReconstructor::camera).
BatchReport reconstruct_files(Reconstructor& engine, const CameraConfig& camera,
                              const std::vector<std::filesystem::path>& captures, const BatchOptions& options);

}  // namespace flatnet
