#include "eval/tables.hpp"

#include <cmath>
#include <iomanip>
#include <sstream>

namespace flatnet {

std::string MarkdownTable::markdown() const {
  std::ostringstream md;
  auto line = [&](const std::vector<std::string>& cells) {
    md << "|";
    for (const auto& c : cells) md << " " << c << " |";
    md << "\n";
  };
  line(header);
  md << "|";
  for (size_t i = 0; i < header.size(); ++i) md << "---|";
  md << "\n";
  for (const auto& r : rows) line(r);
  return md.str();
}

std::string fixed(double value, int digits) {
  if (!std::isfinite(value)) return "-";
  std::ostringstream s;
  s << std::fixed << std::setprecision(digits) << value;
  return s.str();
}

std::string scientific(double value, int digits) {
  if (!std::isfinite(value)) return "-";
  std::ostringstream s;
  s << std::scientific << std::setprecision(digits) << value;
  return s.str();
}

std::string plus_minus(double mean, double sd, int digits) {
  if (!std::isfinite(mean)) return "-";
  return fixed(mean, digits) + " ± " + fixed(sd, digits);
}

torch::Tensor with_inset(const torch::Tensor& image, int64_t row, int64_t col, int64_t size, int64_t zoom) {
  TORCH_CHECK(image.dim() == 3 && image.size(0) == 3, "with_inset: {3,H,W} expected");
  const int64_t H = image.size(1), W = image.size(2), big = size * zoom;
  TORCH_CHECK(row >= 0 && col >= 0 && row + size <= H && col + size <= W && big + 2 <= std::min(H, W),
              "with_inset: the detail or its inset does not fit the image");
  auto out = image.to(torch::kFloat32).clone();
  const auto detail = out.slice(1, row, row + size).slice(2, col, col + size).clone();
  const auto magnified = detail.repeat_interleave(zoom, 1).repeat_interleave(zoom, 2);  // nearest: pixels stay visible
  const auto yellow = torch::tensor({1.0f, 1.0f, 0.0f}).view({3, 1, 1});
  auto frame = [&](int64_t r0, int64_t c0, int64_t h, int64_t w) {  // a 1-pixel frame inside the box
    out.slice(1, r0, r0 + 1).slice(2, c0, c0 + w).copy_(yellow.expand({3, 1, w}));
    out.slice(1, r0 + h - 1, r0 + h).slice(2, c0, c0 + w).copy_(yellow.expand({3, 1, w}));
    out.slice(1, r0, r0 + h).slice(2, c0, c0 + 1).copy_(yellow.expand({3, h, 1}));
    out.slice(1, r0, r0 + h).slice(2, c0 + w - 1, c0 + w).copy_(yellow.expand({3, h, 1}));
  };
  const int64_t r0 = H - big - 1, c0 = W - big - 1;
  out.slice(1, r0, r0 + big).slice(2, c0, c0 + big).copy_(magnified);
  frame(r0 - 1, c0 - 1, big + 2, big + 2);
  frame(row, col, size, size);
  return out;
}

}  // namespace flatnet
