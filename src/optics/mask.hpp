#pragma once
// Learnable separable-rank amplitude masks and the lensless capture model used to design them
// (FlatNet thesis, ch. "learning the mask"): a mask of E x E elements, each covering
// `upsample` x `upsample` sensor pixels; the PSF is the mask's centred sensor-sized window,
//   p = M_window / (0.5 * rows * cols)          (unit DC gain for a half-open mask),
// and a capture is the circular convolution of the scene, centred on a sensor-sized canvas, with
// p (FFT, PSF centre at the origin), plus noise.
#include <string>

#include <torch/torch.h>

namespace flatnet {

enum class MaskProjection { sigmoid, clamp };    // how U V^T becomes a transmittance
enum class ThroughputRule { equal, cap, free };  // mean transmittance held at, capped at, or free of the target
enum class MaskInit { random, mls };
// Config strings -> enums, once, where configs are read; errors name `key`.
MaskProjection parse_mask_projection(const std::string& s, const std::string& key = "mask.projection");
ThroughputRule parse_throughput_rule(const std::string& s, const std::string& key = "mask.throughput");
MaskInit parse_mask_init(const std::string& s, const std::string& key = "mask.init");

struct MaskOptions {
  int64_t elements = 511;          // mask elements per side
  int64_t rank = 1;                // M = project(U V^T), U and V {elements, rank}
  int64_t upsample = 4;            // sensor pixels per mask element (nearest)
  int64_t rows = 500, cols = 620;  // sensor
  MaskProjection projection = MaskProjection::sigmoid;
  ThroughputRule throughput = ThroughputRule::equal;  // equal: held at target; cap: <= target; free
  double target = 0.5;
  bool binary = false;               // straight-through binarisation (open where M > its median)
  MaskInit init = MaskInit::random;  // random, or the MLS mask's vectors
  uint64_t seed = 0;
};

class MaskModelImpl : public torch::nn::Module {
 public:
  explicit MaskModelImpl(const MaskOptions& options);
  // Transmittance of every element {E,E}, in [0,1], with the throughput rule applied.
  torch::Tensor transmittance();
  // The sensor-sized window of the upsampled mask {rows, cols}.
  torch::Tensor window();
  torch::Tensor U, V;
  const MaskOptions& options() const { return opt_; }

 private:
  MaskOptions opt_;
};
TORCH_MODULE(MaskModel);

// Centred {rows, cols} window of a mask {E,E} upsampled by `upsample` (nearest); regions the
// mask does not cover are opaque (0).
torch::Tensor mask_window(const torch::Tensor& mask, int64_t upsample, int64_t rows, int64_t cols);

// Baseline masks as element grids {E,E} in {0,1}:
// MLS: 511-element +-1 maximum-length sequence, outer product with itself, -1 -> 0.
torch::Tensor mls_mask();
// FlatNet's "02": the 31-element pattern's outer product ({31,31}); with upsample 4 it covers
// 124x124 sensor pixels and the rest of the window is opaque.
torch::Tensor m02_mask();

// Throughput: the mean transmittance of a window.
double throughput(const torch::Tensor& window);

// ---- Capture and Wiener deconvolution ------------------------------------------------------------
struct WienerCamera {
  int64_t rows = 500, cols = 620;  // sensor / canvas
  int64_t scene = 256;             // scene side, placed in the canvas centre
  double noise_sigma = 3e-4;       // Gaussian read noise on the capture
  double photons = 0;              // > 0: Poisson noise with this many photons at unit signal
};

// PSF p = window / (0.5 rows cols), shifted so its centre is at the origin, as its 2-D real FFT.
torch::Tensor psf_spectrum(const torch::Tensor& window);  // {rows, cols/2+1} complex
// Scenes {B,N,N} -> noisy captures {B,rows,cols}.
torch::Tensor capture(const torch::Tensor& scenes, const torch::Tensor& P, const WienerCamera& cam,
                      c10::optional<at::Generator> gen = c10::nullopt);
// Wiener: x = F^-1{ conj(P) / (|P|^2 + gamma) F{y} }, centred N x N crop. {B,rows,cols} -> {B,N,N}.
torch::Tensor wiener(const torch::Tensor& y, const torch::Tensor& P, const torch::Tensor& gamma,
                     const WienerCamera& cam);

// Mask for a name: "mls", "m02", or a 16-bit PNG (65535 = fully transparent) of the sensor window.
// Errors name the file: wrong size, values outside [0,1], not 16-bit.
torch::Tensor load_mask_window(const std::string& what, const WienerCamera& cam, int64_t upsample = 4);

}  // namespace flatnet
