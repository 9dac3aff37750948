#pragma once
// One moving shadow: column j is a +-1 code shifted by j sensor pixels (the FlatCam's Toeplitz factor),
// each column less its mean: the factor of the double-centred planes, as a calibration holds it.
#include <torch/torch.h>

namespace test {

inline torch::Tensor shadow_factor(int64_t rows, int64_t scene, uint64_t seed) {  // {rows, scene}
  auto gen = at::detail::createCPUGenerator(seed);
  const int64_t length = rows - scene + 1;
  const auto code = (at::rand({length}, gen) > 0.5).to(torch::kFloat32) * 2 - 1;
  auto P = torch::zeros({rows, scene});
  for (int64_t j = 0; j < scene; ++j) P.narrow(0, j, length).select(1, j).copy_(code);
  return P - P.mean(0, true);
}

}  // namespace test
