#pragma once
// What the reports share (`flatnet report`, `flatnet mask report`): Markdown tables with formatted
// numbers, and figure tiles with a magnified detail.
#include <string>
#include <vector>

#include <torch/torch.h>

namespace flatnet {

struct MarkdownTable {
  std::vector<std::string> header;
  std::vector<std::vector<std::string>> rows;
  void add(std::vector<std::string> row) { rows.push_back(std::move(row)); }
  std::string markdown() const;  // "| a | b |\n|---|---|\n| ... |\n"
};

std::string fixed(double value, int digits);                 // "-" for NaN
std::string scientific(double value, int digits);            // "1.00e-06"
std::string plus_minus(double mean, double sd, int digits);  // "19.66 ± 3.33", "-" for NaN

// {3,H,W} image with the size x size detail at (row, col) magnified `zoom` times into its
// bottom-right corner, framed in yellow; the detail's place is framed too (thesis Figure 5.1's insets).
torch::Tensor with_inset(const torch::Tensor& image, int64_t row, int64_t col, int64_t size, int64_t zoom = 2);

}  // namespace flatnet
