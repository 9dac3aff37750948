#pragma once
// The thesis's Figure 3.3: what FlatNet's trainable inversion learns. For the first stage
// X = W1^T Y W2 and a separable camera Y = PhiL X PhiR^T, the stage sees X through the products
// W1^T PhiL and W2^T PhiR ({N,N} each): identity would be a perfect inverse. They are shown as
// images before training (the initialisation the model's config describes: the calibration's
// transpose, or calibration-free pseudo-random matrices) and after (the model's weights), with the
// share of their energy on and near the diagonal.
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include <torch/torch.h>

namespace flatnet {

struct ProductStats {
  double diagonal = 0;  // sum of squared diagonal entries / sum of all squared entries
  // The same within 2 of the diagonal i - j = offset, at the offset where it is largest: a learned
  // inversion may reproduce the scene shifted (calibration-free models do), which is still an inverse.
  double band = 0;
  int64_t offset = 0;
  // Output rows whose band (at that offset) holds under a quarter of the row's energy: rows the
  // inversion does not invert, so they mix far-away scene rows; the enhancer sees a whole-row error
  // there, and a model with such rows draws a stripe at them (issue: calibration-free stripes).
  std::vector<int64_t> stray_rows;
};
// "3, 28-30, 164-173": sorted indices as ranges ("none" when empty).
std::string index_ranges(const std::vector<int64_t>& sorted);
// W {rows,N}, Phi {rows,N} -> W^T Phi {N,N} and its statistics.
std::pair<torch::Tensor, ProductStats> inversion_product(const torch::Tensor& W, const torch::Tensor& Phi);

struct InversionReportOptions {
  std::vector<std::pair<std::string, std::filesystem::path>> models;  // NAME, model file
  std::filesystem::path out;                                          // inversion.md, inversion.png
  // The calibration PhiL, PhiR come from here (a model file carries its camera's preprocessing but
  // not its calibration): the camera the models were trained for.
  std::filesystem::path calibration;
};

// Writes OUT/inversion.md (a table per model: left and right products, before and after, diagonal
// and band shares) and OUT/inversion.png (a row per model: |W1^T PhiL| and |W2^T PhiR| before and
// after, each scaled to its largest entry). Returns the Markdown. PhiL and PhiR are the channel of
// the calibration named by model.inversion.channel (gb for FlatNet). Models with a
// Tikhonov first stage have no trainable inversion and are refused.
std::string write_inversion_report(const InversionReportOptions& options);

}  // namespace flatnet
