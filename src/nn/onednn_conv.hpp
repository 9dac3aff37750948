#pragma once
// A 2-D convolution for bf16 inference, run by oneDNN directly (the same libdnnl LibTorch uses).
// LibTorch 1.13 hands oneDNN plain weights on every call, and oneDNN reorders them into its AMX
// kernel's blocked layout each time (14.5 ms of a 190 ms paper-width pass, most of it in the deep
// 1024-channel layers); its ReLU is a second pass over every output. Here the weights are reordered
// once per input shape, and bias and ReLU are fused into the convolution (oneDNN post-op).
// Activations stay LibTorch tensors in channels-last bf16 (NHWC), so no activation is reordered.
#include <array>
#include <atomic>
#include <map>
#include <memory>

#include <torch/torch.h>

namespace flatnet {

struct OneDnnConvOptions {
  int64_t stride = 1, padding = 0;
  bool relu = false;  // max(0, .) fused after the bias
};

class OneDnnConv {
 public:
  // weight {O,I,kh,kw} (shared when already bf16 channels-last, as after the bf16 and channels-last
  // levers), bias {O} or undefined (kept in fp32).
  OneDnnConv(const torch::Tensor& weight, const torch::Tensor& bias, const OneDnnConvOptions& options);
  ~OneDnnConv();
  // {B,I,H,W} bf16 (any memory format; made channels-last) -> {B,O,H',W'} bf16 channels-last.
  torch::Tensor operator()(const torch::Tensor& x);
  // Convolutions built so far in this process (tests check that a lever took effect).
  static int64_t built();

 private:
  struct Plan;
  Plan& plan_for(int64_t batch, int64_t height, int64_t width);
  torch::Tensor weight_, bias_;  // bf16 {O,I,kh,kw} channels-last, fp32 {O}
  int64_t in_channels_, out_channels_;
  OneDnnConvOptions opt_;
  std::map<std::array<int64_t, 3>, std::unique_ptr<Plan>> plans_;  // by input (B, H, W)
};

// What onednn_bmm multiplies: fp32 operands, or the operands rounded to bf16 (8 significant bits)
// with fp32 accumulation and an fp32 result, about twice as fast where the CPU runs bf16 natively.
enum class GemmOperands { fp32, bf16 };

// C = A B for batches of matrices, {batch,M,K} x {batch,K,N} -> {batch,M,N} fp32 (either operand
// may have batch 1, broadcast), by a oneDNN matmul primitive made once per shape and reused. On
// AVX-512 machines oneDNN's fp32 GEMM kernels run about twice as fast as OpenBLAS's at the
// Tikhonov reconstruction's shapes (`flatnet bench --rows peak,tikhonov`). Inference only: no autograd.
// bf16 operands only where cpu_features().native_bf16() (AVX512-BF16 or AMX, oneDNN not capped below
// them: cpu_features folds the cap in); an error elsewhere.
torch::Tensor onednn_bmm(const torch::Tensor& a, const torch::Tensor& b, GemmOperands operands = GemmOperands::fp32);
// The work flatnet's own oneDNN calls have done since the process started, in FLOPs (2 per
// multiply-add): onednn_bmm's products and onednn_conv2d's passes (its forward, and each gradient
// it computes). LibTorch's profiler counts only ATen's operators, so `flatnet bench` adds this
// counter's rise over a counted run (count_gflop). In the profiler's tables they show as
// flatnet::onednn_bmm and flatnet::onednn_conv2d.
uint64_t onednn_flops();
// The same product, differentiable: its backward is two more oneDNN GEMMs (dA = dC B^T and
// dB = A^T dC, summed over a broadcast batch, with the forward's operand type; the gradients are
// fp32 either way). What FlatNet's first stage trains with.
torch::Tensor onednn_matmul_autograd(const torch::Tensor& a, const torch::Tensor& b,
                                     GemmOperands operands = GemmOperands::fp32);

// The activation after a training-mode batch norm: ReLU (the U-Net) or swish, z sigmoid(z) (the
// discriminator).
enum class NormActivation { relu = 0, swish = 1 };

// Training-mode batch norm and the activation after it by oneDNN, one primitive each way for ReLU
// (fuse_norm_relu) and two for swish (batch norm, then eltwise_swish); LibTorch 1.13 runs batch norm,
// the activation and their backward as four to seven passes over the activations:
//   y = act(weight (x - mean) / sqrt(var + eps) + bias),  mean and (biased) var over {B,H,W},
// as torch::batch_norm in training mode then the activation. running_mean and running_var move by
// `momentum` towards the batch's mean and unbiased variance, as LibTorch's do. Gradients reach x,
// weight and bias. x {B,C,H,W}: channels-last, fp32 or bf16 (weight, bias and the statistics fp32).
torch::Tensor onednn_batch_norm_activation(const torch::Tensor& x, const torch::Tensor& weight,
                                           const torch::Tensor& bias, torch::Tensor running_mean,
                                           torch::Tensor running_var, double momentum, double eps,
                                           NormActivation activation);
// Whether onednn_batch_norm_activation runs x here: a CPU {B,C,H,W} channels-last fp32 or bf16
// tensor, more than one value per channel, and a oneDNN kernel for its type on this CPU (bf16 needs
// AVX-512). The primitives it makes for (x, eps, activation) are kept for the call that follows.
bool onednn_batch_norm_runs(const torch::Tensor& x, double eps = 1e-5,
                            NormActivation activation = NormActivation::relu);
// A module's batch norm, then the activation: through onednn_batch_norm_activation in training
// where it runs (counting num_batches_tracked as BatchNorm2d does), else the module's own forward
// and LibTorch's activation (eval, no affine weights or running statistics, channels-first input).
torch::Tensor batch_norm_activation(torch::nn::BatchNorm2dImpl& bn, const torch::Tensor& x, NormActivation activation);

// A 2-D convolution for training, run by oneDNN directly: y = conv(x, weight) + bias, with the
// gradients of x, weight and bias. LibTorch 1.13 hands oneDNN's backward NHWC activations with
// primitives made without the forward's hint; under oneDNN's AVX2 kernels that runs the backward at
// 3-6x the forward (32->16 channels at 256x256, batch 4: 107 ms against 16.6). Here the three
// primitives are made once per shape with the forward's hint, and the weight gradient reads the
// layout its kernel asks for (see weight_gradient_wants_blocked). x {B,I,H,W}: channels-last, fp32 or
// bf16; weight {O,I,kh,kw} and bias {O} (or undefined): fp32, any layout; the weight's gradient
// comes back fp32 in its layout. Square stride and padding, no dilation or groups.
torch::Tensor onednn_conv2d(const torch::Tensor& x, const torch::Tensor& weight, const torch::Tensor& bias,
                            int64_t stride, int64_t padding);
// Whether onednn_conv2d takes these: the types and layouts above, and a oneDNN kernel for them on
// this CPU other than a reference loop (bf16 needs AVX-512). Its primitives are kept for the call.
bool onednn_conv2d_runs(const torch::Tensor& x, const torch::Tensor& weight, const torch::Tensor& bias, int64_t stride,
                        int64_t padding);
// A module's convolution: through onednn_conv2d in fp32 where a gradient is wanted and it runs, else
// the module's own forward (under autocast, bf16, LibTorch's convolutions train as fast).
torch::Tensor convolve(torch::nn::Conv2dImpl& conv, const torch::Tensor& x);

}  // namespace flatnet
