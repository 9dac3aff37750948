#pragma once
// FlatNet-sep (Khan et al., ICCV 2019 / TPAMI 2020): a trainable inversion of the separable
// FlatCam model followed by a perceptual-enhancement network. Module and parameter names follow
// FlatNet's models.py (PhiL, PhiR, bn, inc, down1..4, up1..4, outc), so that, with the prefixes
// `inversion.` and `enhancer.` dropped, a state_dict interchanges with FlatNet's own release.
#include <functional>
#include <string>

#include <torch/torch.h>

#include "io/camera_config.hpp"
#include "nn/enhancers.hpp"
#include "nn/onednn_conv.hpp"

namespace flatnet {

// ---- Trainable inversion ------------------------------------------------------------------------
// Per Bayer channel c:  X_c = leaky_relu(PhiL_c^T Y_c PhiR_c)   (FlatNet eq. 3, W1 = PhiL, W2 = PhiR)
// PhiL {rows, N, k}, PhiR {cols, N, k} with k = 1 (one pair shared by the four channels, as
// FlatNet) or k = 4 (one pair per channel). The output channels are in FlatNet's order
// (r, gr, gb, b): the input planes (b, gb, gr, r) reversed.
struct InversionOptions {
  torch::Tensor phil;  // {rows, N, k} initial W1
  torch::Tensor phir;  // {cols, N, k} initial W2
  double negative_slope = 0.01;
};

class FlatInversionImpl : public torch::nn::Module {
 public:
  explicit FlatInversionImpl(const InversionOptions& options);
  torch::Tensor forward(const torch::Tensor& Y);  // {B,4,rows,cols} -> {B,4,N,N}
  // Only the size x size window at corners[b] = (row, col) of sample b's output: the same numbers
  // as forward(Y) sliced, from the matching columns of PhiL and PhiR (a fraction of the work).
  torch::Tensor forward_crops(const torch::Tensor& Y, const std::vector<std::pair<int64_t, int64_t>>& corners,
                              int64_t size);  // {B,4,rows,cols} -> {B,4,size,size}
  // What the products W1^T Y W2 take: fp32, or operands rounded to bf16 (fp32 accumulation and
  // result), which bf16 training sets where the CPU runs bf16 natively (GeneratorImpl::set_autocast_bf16).
  void set_product_operands(GemmOperands operands) { operands_ = operands; }
  torch::Tensor PhiL, PhiR;

 private:
  double negative_slope_;
  GemmOperands operands_ = GemmOperands::fp32;
};
TORCH_MODULE(FlatInversion);

// Fixed Tikhonov reconstruction as a module (the "naive" baseline's first stage): the SVD filter
// of eq. 2.6 held as buffers, so a model file carries it. Output order (r, gr, gb, b) like the
// inversion's.
class TikhonovLayerImpl : public torch::nn::Module {
 public:
  // P {4,rows,N}, Q {4,cols,N} (a calibration), lambda the regulariser.
  TikhonovLayerImpl(const torch::Tensor& P, const torch::Tensor& Q, double lambda);
  // Shapes only (weights follow from a checkpoint or model file).
  TikhonovLayerImpl(int64_t rows, int64_t cols, int64_t n);
  torch::Tensor forward(const torch::Tensor& Y);  // {B,4,rows,cols} -> {B,4,N,N}

 private:
  torch::Tensor ULt_, UR_, VL_, VRt_, filter_;
};
TORCH_MODULE(TikhonovLayer);

// ---- Measurement pre-processor ------------------------------------------------------------------
// A small residual CNN on the measurement planes before the first stage: the pre-processor of
// LenslessPiCam's modular reconstruction (Perron et al., IEEE TCI 2025), which learns where the
// sensor's noise is still white and before the inversion spreads a defect over the whole image:
//   Y' = Y + g(Y),  g = conv_depth o (leaky_relu o conv_i)...  (3x3, 4 -> width -> 4).
// No biases, so g is positively homogeneous (g(aY) = a g(Y), a > 0): it treats a capture alike at
// every exposure. Its last convolution starts at zero, so a new pre-processor is the identity and
// a trained model gains one without changing what it computes (train --init-from).
struct PreprocessorOptions {
  int64_t width = 0;  // 0: none
  int64_t depth = 2;  // convolutions, >= 2
  double negative_slope = 0.01;
};

class MeasurementPreprocessorImpl : public torch::nn::Module {
 public:
  explicit MeasurementPreprocessorImpl(const PreprocessorOptions& options);
  torch::Tensor forward(const torch::Tensor& Y);  // {B,4,rows,cols} -> {B,4,rows,cols}

 private:
  double negative_slope_;
  torch::nn::ModuleList convs_;
};
TORCH_MODULE(MeasurementPreprocessor);

// ---- The generator -------------------------------------------------------------------------------
enum class InputStage { inversion, tikhonov };
enum class Enhancer { unet, dncnn, rcan, nafnet };

struct GeneratorOptions {
  InputStage input = InputStage::inversion;
  PreprocessorOptions preprocessor;  // on the planes, before the first stage (width 0: none)
  InversionOptions inversion;        // input == inversion
  torch::Tensor tik_P, tik_Q;        // input == tikhonov: calibration {4,rows,N},{4,cols,N}
  double tik_lambda = 1e-4;
  int64_t rows = 500, cols = 620, scene = 256;  // measurement and scene sizes (for shape checks)
  Enhancer enhancer = Enhancer::unet;
  UNetOptions unet;
  DnCNNOptions dncnn;
  RCANOptions rcan;
  NAFNetOptions nafnet;
  double bn_momentum = 0.99;  // the BatchNorm2d(4) between the stages
  // Light level as an input (camera centring "level"): each measurement plane's mean is removed
  // before the first stage and given to the enhancer as four constant channels beside the
  // first stage's four. Without it a flat capture, black or saturated white, is all zeros after
  // double centring, and the network cannot tell a dark scene from a bright one.
  bool level_input = false;
};

// Throws unless the camera's preprocessing gives what the model was built for: the crop and
// scene sizes, and the light level (centring "level") exactly when the model reads it.
void check_camera_for_model(const GeneratorOptions& model, const CameraConfig& camera);

// Inference-only speed-ups (each measured by `flatnet bench --levers`, README "Speed"):
//  - fold_batchnorm: eval-mode BN folded into the U-Net's convolutions, ReLUs in place;
//  - channels_last: NHWC activations and weights (oneDNN's native layout);
//  - gemm_upsample: the U-Net's 2x2 stride-2 transposed convolutions as one GEMM each;
//  - bf16: the enhancer in bfloat16 (AVX-512-BF16), the inversion stays float32;
//  - onednn (with bf16 and fold): the U-Net's convolutions run by oneDNN directly, weights
//    prepacked once and bias + ReLU fused (nn/onednn_conv.hpp).
// prepare_inference changes the module in place: never train or save it afterwards.
struct InferenceLevers {
  bool fold_batchnorm = true;
  bool channels_last = true;
  bool bf16 = false;
  bool gemm_upsample = true;
  bool onednn = true;
  // Not a speed-up and not exact (so not in parse_inference_levers's list): test-time
  // self-ensemble, the enhancer run on the first stage's image and its horizontal, vertical and
  // double flips (one batch of 4B), each output flipped back and the four images averaged.
  // About 4x the enhancer's time; `infer --self-ensemble`.
  bool self_ensemble = false;
  // onednn acts only on folded bf16 models.
  // oneDNN's own bf16 convolutions need its bf16 kernels (AVX-512 and up, no ISA cap).
  bool onednn_active() const;
};
// Test-time self-ensemble (Timofte et al. 2016): the mean over the identity and the horizontal,
// vertical and double flips T of T^-1(f(T(x))), with f run once on the four views as one batch.
// x {B,C,H,W} -> {B,C',H,W}; a flip-equivariant f gives f(x).
torch::Tensor flip_ensemble(const std::function<torch::Tensor(const torch::Tensor&)>& f, const torch::Tensor& x);

// "none" or a comma list of fold, channels-last, gemm-up, bf16, onednn.
InferenceLevers parse_inference_levers(const std::string& s);
// The speed-ups on, as parse_inference_levers reads them ("none" when none; self_ensemble is not one).
std::string inference_levers_text(const InferenceLevers& l);

// The module's 4-D parameters (convolution weights) in channels-last order, the layout oneDNN
// convolves fastest; the values are unchanged.
void weights_to_channels_last(torch::nn::Module& module);

class GeneratorImpl : public torch::nn::Module {
 public:
  explicit GeneratorImpl(const GeneratorOptions& options);
  // {B,4,rows,cols} measurement planes -> {B,3,N,N} sRGB image in [0,1].
  torch::Tensor forward(const torch::Tensor& Y);
  // Training on crops: the first stage computes only the size x size window at corners[b] of
  // sample b (the inversion still sees the whole capture), and the enhancer runs on those windows.
  torch::Tensor forward_crops(const torch::Tensor& Y, const std::vector<std::pair<int64_t, int64_t>>& corners,
                              int64_t size);  // -> {B,3,size,size}
  // The first stage alone, {B,4,N,N} (for inspection and the sample grid; without the level).
  torch::Tensor first_stage(const torch::Tensor& Y);
  const GeneratorOptions& options() const { return options_; }
  // Applies inference levers (eval mode; see InferenceLevers). Irreversible.
  void prepare_inference(const InferenceLevers& levers);
  // The levers that keep training exact (channels_last, gemm_upsample); call before making the optimiser.
  void prepare_training(const InferenceLevers& levers);
  // Mixed precision for training: the BN and enhancer run under bf16 autocast (weights, their
  // gradients and Adam's state stay fp32); the inversion's matmuls round their operands to bf16 where
  // oneDNN runs bf16 natively, accumulating and returning fp32; the output sigmoid stays fp32.
  // Where oneDNN has no bf16 kernels this also switches LibTorch's oneDNN path off for the process
  // (core/precision: the backward pass runs outside any scope the forward pass holds).
  void set_autocast_bf16(bool on);
  bool autocast_bf16() const { return autocast_bf16_; }

 private:
  GeneratorOptions options_;
  void check_measurement(const torch::Tensor& Y) const;
  // {B,4,H,W} first-stage output (+ {B,4,1,1} light level when level_input) -> {B,3,H,W} in [0,1]
  torch::Tensor enhance(const torch::Tensor& first, const torch::Tensor& level);
  // The enhancer's input {B,C,H,W} -> the mean of its four flipped runs, {B,3,H,W} in [0,1]
  // (InferenceLevers::self_ensemble).
  torch::Tensor self_ensemble(const torch::Tensor& x);
  // {B,4,rows,cols} -> the planes without their DC and {B,4,1,1} the DC, in the first stage's
  // channel order (r, gr, gb, b); an undefined level without level_input.
  std::pair<torch::Tensor, torch::Tensor> split_level(const torch::Tensor& Y) const;
  torch::Tensor first_stage_of(const torch::Tensor& planes);  // inversion or Tikhonov, on planes without the level
  torch::Tensor preprocessed(const torch::Tensor& planes);    // the pre-processor's output, or the planes
  void apply_levers(const InferenceLevers& levers, bool for_inference);
  bool autocast_bf16_ = false;
  InferenceLevers levers_{false, false, false, false, false};
  MeasurementPreprocessor preprocessor_{nullptr};  // null without one
  FlatInversion inversion_{nullptr};
  TikhonovLayer tikhonov_{nullptr};
  torch::nn::BatchNorm2d bn_{nullptr};
  torch::nn::AnyModule enhancer_;
};
TORCH_MODULE(Generator);

// The size x size window at corners[b] = (row, col) of each image b: {B,C,H,W} -> {B,C,size,size}.
// No corners: the images as they are.
torch::Tensor crop_windows(const torch::Tensor& images, const std::vector<std::pair<int64_t, int64_t>>& corners,
                           int64_t size);

InputStage parse_input_stage(const std::string& s);
Enhancer parse_enhancer(const std::string& s);

}  // namespace flatnet
