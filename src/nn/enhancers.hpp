#pragma once
// The enhancers that follow FlatNet's first stage: the U-Net of FlatNet's models.py (module names
// inc, down1..4, up1..4, outc, so that a state_dict interchanges with FlatNet's release), and the
// thesis's ablation enhancers DnCNN and RCAN, and NAFNet. Each maps {B,C,H,W} -> {B,3,H,W} logits.
#include <memory>
#include <vector>

#include <torch/torch.h>

namespace flatnet {

// ---- U-Net (FlatNet's models.py) ----------------------------------------------------------------
struct UNetOptions {
  int64_t in_channels = 4;
  int64_t out_channels = 3;
  int64_t width = 128;        // first level's filters; 128 is the paper
  double bn_momentum = 0.99;  // PyTorch convention (new = (1-m) old + m batch), as FlatNet
};

class UNetImpl : public torch::nn::Module {
 public:
  explicit UNetImpl(const UNetOptions& options);
  torch::Tensor forward(const torch::Tensor& x);  // {B,in,H,W} -> {B,out,H,W} logits (H, W divisible by 16)

  // The inference levers (nn/generator.hpp, InferenceLevers) on the U-Net's own blocks:
  // each double conv's eval-mode batch norm folded into its convolutions (inference only);
  void fold_batchnorm();
  // the transposed convolutions' upsampling as one GEMM, its weights cached when for inference;
  void set_upsampling(bool gemm, bool cache_weights);
  // the folded convolutions and the last one run by oneDNN with prepacked weights (bf16 inference).
  void use_onednn();

 private:
  torch::nn::AnyModule inc_, down1_, down2_, down3_, down4_;
  std::vector<std::shared_ptr<torch::nn::Module>> ups_;
  torch::nn::AnyModule outc_;
};
TORCH_MODULE(UNet);

// ---- DnCNN (Zhang et al. 2017), thesis ablation -------------------------------------------------
struct DnCNNOptions {
  int64_t in_channels = 4, out_channels = 3;
  int64_t layers = 19;  // conv-ReLU, (layers-2) x conv-BN-ReLU, conv
  int64_t width = 64;
  double bn_momentum = 0.1;
};
class DnCNNImpl : public torch::nn::Module {
 public:
  explicit DnCNNImpl(const DnCNNOptions& options);
  torch::Tensor forward(const torch::Tensor& x);  // {B,in,H,W} -> {B,out,H,W} logits
 private:
  torch::nn::Sequential body_;
};
TORCH_MODULE(DnCNN);

// ---- RCAN (Zhang et al. 2018) without upsampling, thesis ablation -------------------------------
struct RCANOptions {
  int64_t in_channels = 4, out_channels = 3;
  int64_t groups = 5, blocks = 10;  // residual groups x residual channel-attention blocks
  int64_t width = 64;
  int64_t reduction = 16;  // channel-attention squeeze ratio
};
class RCANImpl : public torch::nn::Module {
 public:
  explicit RCANImpl(const RCANOptions& options);
  torch::Tensor forward(const torch::Tensor& x);  // {B,in,H,W} -> {B,out,H,W} logits
 private:
  torch::nn::Conv2d head_{nullptr}, body_end_{nullptr}, tail_{nullptr};
  torch::nn::ModuleList groups_;
};
TORCH_MODULE(RCAN);

// ---- NAFNet (Chen et al., ECCV 2022), a modern enhancer ----------------------------------------
// A U-shaped network of NAFBlocks: LayerNorm over channels, 1x1 conv to 2c, 3x3 depthwise conv,
// SimpleGate (one half times the other), simplified channel attention (global mean, 1x1 conv,
// multiply), 1x1 conv, a residual scaled by beta; then a gated 1x1 feed-forward scaled by gamma
// (beta and gamma start at 0, so every block starts as the identity). Down: 2x2 stride-2 conv to
// 2c; up: 1x1 conv to 2c and pixel shuffle; skips are added. Four levels (H, W divisible by 16).
// Parameter names as the authors' NAFNet_arch.py (intro, encoders, downs, middle_blks, ups,
// decoders, ending), without its input residual (the output has other channels than the input).
struct NAFNetOptions {
  int64_t in_channels = 4, out_channels = 3;
  int64_t width = 16;         // first level's channels; 2x per level down
  int64_t enc_blocks = 1;     // NAFBlocks per encoder level (the paper: 1, 1, 1, 28 at width 32)
  int64_t middle_blocks = 1;  // at the lowest resolution
  int64_t dec_blocks = 1;     // per decoder level
};
class NAFNetImpl : public torch::nn::Module {
 public:
  explicit NAFNetImpl(const NAFNetOptions& options);
  torch::Tensor forward(const torch::Tensor& x);  // {B,in,H,W} -> {B,out,H,W} logits
 private:
  torch::nn::Conv2d intro_{nullptr}, ending_{nullptr};
  torch::nn::ModuleList encoders_, downs_, ups_, decoders_;
  torch::nn::Sequential middle_{nullptr};
};
TORCH_MODULE(NAFNet);

// Layer normalisation over the channels of each pixel (NAFNet's LayerNorm2d), eps 1e-6:
// weight * (x - mean_c) / sqrt(var_c + eps) + bias.  {B,C,H,W} -> {B,C,H,W}
class LayerNorm2dImpl : public torch::nn::Module {
 public:
  explicit LayerNorm2dImpl(int64_t channels);
  torch::Tensor forward(const torch::Tensor& x);
  torch::Tensor weight, bias;
};
TORCH_MODULE(LayerNorm2d);

}  // namespace flatnet
