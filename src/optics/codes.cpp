#include "optics/codes.hpp"

#include "core/error.hpp"
#include "io/mat.hpp"

namespace flatnet {

std::vector<int> mls(int n) {
  // Taps of primitive polynomials (Xilinx XAPP052 table), 1-based bit positions.
  static const std::map<int, std::vector<int>> taps = {
      {2, {2, 1}},         {3, {3, 2}},         {4, {4, 3}},           {5, {5, 3}},    {6, {6, 5}},
      {7, {7, 6}},         {8, {8, 6, 5, 4}},   {9, {9, 5}},           {10, {10, 7}},  {11, {11, 9}},
      {12, {12, 6, 4, 1}}, {13, {13, 4, 3, 1}}, {14, {14, 5, 3, 1}},   {15, {15, 14}}, {16, {16, 15, 13, 4}},
      {17, {17, 14}},      {18, {18, 11}},      {19, {19, 6, 2, 1}},   {20, {20, 17}}, {21, {21, 19}},
      {22, {22, 21}},      {23, {23, 18}},      {24, {24, 23, 22, 17}}};
  auto it = taps.find(n);
  if (it == taps.end()) throw Error("mls: order n must be within 2..24 (length 2^n - 1), got " + std::to_string(n));
  const uint32_t length = (1u << n) - 1;
  uint32_t state = 1;
  std::vector<int> seq(length);
  for (uint32_t i = 0; i < length; ++i) {
    const uint32_t out = state & 1u;
    seq[i] = out ? 1 : -1;
    uint32_t fb = 0;
    for (int t : it->second) fb ^= (state >> (n - t)) & 1u;
    state = (state >> 1) | (fb << (n - 1));
  }
  return seq;
}

std::vector<int> flatnet_m02_pattern() {
  const std::string s = "1110001011100100001111111111111";
  std::vector<int> v;
  for (char c : s) v.push_back(c == '1' ? 1 : 0);
  return v;
}

torch::Tensor hadamard(int64_t n) {
  if (n < 1 || (n & (n - 1)) != 0) throw Error("hadamard: size must be a power of two, got " + std::to_string(n));
  auto H = torch::ones({1, 1}, torch::kFloat64);
  while (H.size(0) < n) H = torch::cat({torch::cat({H, H}, 1), torch::cat({H, -H}, 1)}, 0);
  return H;
}

torch::Tensor toeplitz_phi(const std::vector<int>& code, const MaskGeometry& g) {
  return toeplitz_phi(std::vector<double>(code.begin(), code.end()), g);
}

torch::Tensor toeplitz_phi(const std::vector<double>& code, const MaskGeometry& g) {
  const int64_t L = static_cast<int64_t>(code.size());
  const int64_t M = g.sensor_pixels, N = g.scene_pixels;
  auto phi = torch::zeros({M, N}, torch::kFloat64);
  auto acc = phi.accessor<double, 2>();
  const int sub = 16;  // sub-samples per pixel for the area average
  for (int64_t j = 0; j < N; ++j) {
    // Mask position (in features) seen at sensor coordinate x (features): shifted per scene pixel.
    const double offset =
        (L - M * g.pixel_pitch_um / g.feature_um) / 2.0 + (j - (N - 1) / 2.0) * g.shift_features_per_pixel;
    for (int64_t i = 0; i < M; ++i) {
      double sum = 0;
      for (int s = 0; s < sub; ++s) {
        const double x = ((i + (s + 0.5) / sub) * g.pixel_pitch_um) / g.feature_um + offset;
        const auto k = static_cast<int64_t>(std::floor(x));
        if (k >= 0 && k < L) sum += code[k];
      }
      acc[i][j] = sum / sub;
    }
  }
  if (g.blur_px > 0) {
    const int64_t radius = static_cast<int64_t>(std::ceil(3 * g.blur_px));
    auto k = torch::arange(-radius, radius + 1, torch::kFloat64);
    k = torch::exp(-0.5 * (k / g.blur_px).pow(2));
    k = k / k.sum();
    // blur along the sensor axis: conv1d over rows, one channel per scene column
    auto x = phi.t().unsqueeze(1);  // {N,1,M}
    phi = torch::conv1d(x, k.view({1, 1, -1}), {}, 1, radius).squeeze(1).t().contiguous();
  }
  return phi;
}

double geometry_slope(const MaskGeometry& g) { return g.shift_features_per_pixel * g.feature_um / g.pixel_pitch_um; }

torch::Tensor calibration_free_phi(int64_t rows, int64_t cols, double slope, uint64_t seed) {
  auto gen = at::detail::createCPUGenerator(seed);
  const int64_t span = rows + static_cast<int64_t>(std::ceil(std::abs(slope) * cols)) + 2;
  auto seq = at::normal(0.0, 1.0, {span}, gen, torch::TensorOptions().dtype(torch::kFloat64));
  auto i = torch::arange(rows, torch::kFloat64).unsqueeze(1);
  auto j = torch::arange(cols, torch::kFloat64).unsqueeze(0);
  // column j is the sequence shifted by j * slope pixels (Toeplitz for integer slopes)
  auto base = slope >= 0 ? torch::floor(i - j * slope + slope * (cols - 1)) : torch::floor(i - j * slope);
  auto phi = seq.index({base.to(torch::kLong)});
  const double smax = torch::linalg_matrix_norm(phi, 2).item<double>();
  return phi * (0.5 / smax);
}

torch::Tensor load_flatnet_toeplitz(const std::filesystem::path& path, const std::string& variable) {
  MatReader mat(path);
  auto t = mat.read(variable);
  require(t.dim() == 3 && t.size(2) == 4, path,
          "variable '" + variable + "' should be rows x 256 x 4 (one matrix per Bayer channel)");
  return t.permute({2, 0, 1}).contiguous();
}

}  // namespace flatnet
