#pragma once
// Hot pixels found from a camera's own captures: a pixel stuck bright (or dark) reads far from its
// same-colour neighbours in every capture, whatever the scene, where a working pixel differs from
// them only by the scene's and the mask's detail and by noise. Over K captures the mean difference
// d = mean_k (x_k - median of its 8 same-colour neighbours) is therefore near 0 for working pixels
// (its spread over the sensor, measured robustly by the MAD, is the mask's fixed detail plus noise
// / sqrt(K)) and far out for a stuck one. A pixel beside a clipped one sits that frame out. On a simulated camera with
// 300 stuck pixels at 40-100 % of full scale, 48 captures put every one above 50 MADs and no working pixel above 5.2.
#include <array>
#include <vector>

#include <torch/torch.h>

namespace flatnet {

struct HotPixelOptions {
  double threshold = 12;  // robust z-score (MADs from the median) above which a pixel is stuck
  int adc_bits = 10;      // a quarter of one ADC step is the smallest MAD counted (a flat, quantised sensor)
};

// Accumulates raw frames {H,W} (full-scale units) and lists the stuck pixels, (row, col) of the
// frame, in row-major order.
class HotPixelFinder {
 public:
  explicit HotPixelFinder(HotPixelOptions options = {}) : options_(options) {}
  void add(const torch::Tensor& raw_unit);
  int64_t frames() const { return frames_; }
  std::vector<std::array<int64_t, 2>> find() const;

 private:
  HotPixelOptions options_;
  torch::Tensor sum_;    // {4,H/2,W/2} float64: the sum of the differences from the neighbours' median
  torch::Tensor count_;  // {4,H/2,W/2} int32: the frames each pixel was judged in (no clipped neighbour)
  int64_t frames_ = 0;
};

// The median of 8 values along dim 1 of x {P,8,N}, the mean of the middle two: {P,N}. Equal to
// sort(1)'s middle two averaged, by a sorting network of elementwise min/max.
torch::Tensor median_of_eight(const torch::Tensor& x);

}  // namespace flatnet
