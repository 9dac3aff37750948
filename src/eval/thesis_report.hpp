#pragma once
// `flatnet report`: the thesis's comparison (Table 5.1 and Figures 5.1 and 5.3) as one command.
// For each held-out set and each method it makes the reconstructions that are not on disk yet
// (so an interrupted report resumes), scores them (PSNR, SSIM, NIQE with the ground truth's NIQE
// as the last row), times them, and writes OUT/report.md with one figure per set.
#include <filesystem>
#include <string>
#include <vector>

#include "io/camera_config.hpp"
#include "nn/generator.hpp"
#include "nn/lpips.hpp"

namespace flatnet {

struct ReportMethod {
  std::string name;             // column and folder name
  std::string kind;             // a calibration method's name (recon/methods.hpp), or "model"
  std::filesystem::path model;  // kind == model: a .flatnet file
};

struct ReportSet {
  std::string name;           // e.g. heldout, dim, lamp
  std::filesystem::path dir;  // a dataset folder: val_meas.txt (or meas/) and gt/
};

struct ReportOptions {
  CameraConfig camera;  // preprocessing and calibration for Tikhonov and TV
  std::vector<ReportMethod> methods;
  std::vector<ReportSet> sets;
  std::filesystem::path out;
  std::filesystem::path niqe_model;  // empty: no NIQE column
  std::string lpips;                 // "alex" | "vgg": an LPIPS column (EvalOptions::lpips); empty: none
  LpipsFiles lpips_files;
  int64_t tv_count = 30;   // TV (FISTA, seconds per capture) on the first N captures of a set (0: all)
  int figure_rows = 4;     // scenes in each set's figure
  InferenceLevers levers;  // for the model methods (bf16 where chosen)
  std::string machine;     // printed beside the timings (CPU model, flags, threads, precision)
  std::string command;     // the command line, printed in the report
  bool progress = true;
};

// "NAME=FILE.flatnet" -> a model method; a calibration method's name ("tikhonov", "tv", any other the
// registry holds, recon/methods.hpp) -> that method.
ReportMethod parse_report_method(const std::string& spec);
// "NAME=DIR" -> a set named NAME; "DIR" -> a set named after the folder.
ReportSet parse_report_set(const std::string& spec);

// Writes OUT/report.md, OUT/<set>_figure.png and the reconstructions under OUT/<set>/<method>/;
// returns the report's Markdown.
std::string make_report(const ReportOptions& options);

}  // namespace flatnet
