#pragma once
// `flatnet eval`: metrics of reconstruction folders against ground truth, as CSV, table and sheet.
#include <cmath>
#include <filesystem>
#include <string>
#include <vector>

#include "nn/lpips.hpp"

namespace flatnet {

struct MethodScore {
  std::string method;
  int64_t count = 0;
  double psnr = 0, ssim = 0;        // means over images
  double psnr_sd = 0, ssim_sd = 0;  // standard deviations over images
  // Mean output value over mean ground-truth value, whole set: 1 keeps the scene's light, > 1
  // brightens (a dark scene turned white shows here), < 1 darkens.
  double brightness = 0;
  // NIQE (eval/niqe.hpp; lower is more natural) over the images where it is defined; NaN without a model.
  double niqe = std::nan(""), niqe_sd = std::nan("");
  // How much of the truth's colourfulness and detail (eval/metrics.hpp) the output keeps: the mean
  // over images of output / truth (images whose truth has none are left out). 1 keeps it all; a
  // blurry grey regressor scores well below 1.
  double colour_kept = std::nan(""), detail_kept = std::nan("");
  // Stripe energy (eval/metrics.hpp, 8-bit codes; lower is better, 0 for the truth): the mean over images.
  double stripes = std::nan("");
  // LPIPS v0.1 (nn/lpips.hpp; lower is closer to the truth) and its backbone; NaN without one.
  double lpips = std::nan(""), lpips_sd = std::nan("");
  std::string lpips_net;
};

// One image's scores under one method (a row of metrics.csv); NaN where undefined.
struct ImageScore {
  std::string image, method;
  double psnr = 0, ssim = 0, niqe = std::nan(""), colour_kept = std::nan(""), detail_kept = std::nan(""),
         lpips = std::nan(""), stripes = std::nan("");
};

struct EvalOptions {
  std::filesystem::path gt;   // ground-truth images
  std::filesystem::path out;  // one method's outputs, or a folder with one subfolder per method
  int sheet_rows = 6;
  std::filesystem::path niqe_model;  // a NIQE model (.mat); empty: no NIQE column
  std::vector<std::string> methods;  // subfolders of `out` to score, in this order (empty: every one, by name)
  std::string lpips;                 // "alex" | "vgg": an LPIPS column with that backbone; empty: none
  LpipsFiles lpips_files;            // its weights (find_lpips_files)
};

// Writes out/metrics.csv (per image and mean rows), out/scores.json (the means, scores_json) and
// out/sheet.png; returns the means. With a
// NIQE model, the last entry is the ground truth itself (method "ground truth", NIQE only).
// With `per_image`, also every image's scores, in metrics.csv's order.
std::vector<MethodScore> evaluate(const EvalOptions& options, std::vector<ImageScore>* per_image = nullptr);
std::string format_table(const std::vector<MethodScore>& scores);
// {"METHOD": {"images": N, "psnr": ..., "psnr_sd", "ssim", "ssim_sd", "brightness", "niqe",
// "colour_kept", "detail_kept", "stripes", "lpips" (+ "lpips_net")}, ...}; a metric that is not defined is null. What a
// model file's recorded scores hold (`flatnet export --scores`).
std::string scores_json(const std::vector<MethodScore>& scores);

}  // namespace flatnet
