#pragma once
// LPIPS, the learned perceptual image patch similarity of Zhang et al. (CVPR 2018), version 0.1
// as the `lpips` Python package computes it (lpips.LPIPS(net=..., version='0.1'), inputs in [-1, 1]):
//   d(x, y) = sum_l mean_{h,w} w_l . (f_l(x) / |f_l(x)| - f_l(y) / |f_l(y)|)^2
// where f_l are five ReLU feature maps of a frozen ImageNet backbone (AlexNet or VGG-16, as
// torchvision defines them), |.| is the L2 norm over channels at each pixel (+1e-10), and w_l >= 0
// are the package's learned 1x1 "linear" layers (its weights/v0.1/alex.pth, vgg.pth). Before the
// backbone the images pass its ScalingLayer: (x - shift) / scale with shift (-.030, -.088, -.188),
// scale (.458, .448, .450). Lower is more similar; 0 for identical images.
//
// The weights are data from two files a user has (nothing is downloaded): torchvision's backbone
// (alexnet-owt-7be5be79.pth or vgg16-397923af.pth, what torch hub caches in
// ~/.cache/torch/hub/checkpoints) and the lpips package's linear layers, read with the project's
// own torch.save reader (io/torch_file.hpp: no code runs, sizes are checked).
#include <filesystem>
#include <string>
#include <vector>

#include <torch/torch.h>

namespace flatnet {

enum class LpipsBackbone { alex, vgg };

LpipsBackbone parse_lpips_backbone(const std::string& name);  // "alex" | "vgg"; else an Error naming both
std::string lpips_backbone_name(LpipsBackbone backbone);

struct LpipsFiles {
  std::filesystem::path backbone;  // torchvision state dict: features.N.weight / bias (classifier ignored)
  std::filesystem::path linear;    // lpips state dict: lin0.model.1.weight ... lin4.model.1.weight, {1,C,1,1}
};

// The folders searched for the files, in order: `dir` if given, then models/lpips under the
// project's data directory, then torch hub's checkpoint cache ($TORCH_HOME/hub/checkpoints, default
// ~/.cache/torch/hub/checkpoints). The backbone is the first torchvision file of its name pattern
// (alexnet-*.pth, vgg16-*.pth); the linear layers are alex.pth or vgg.pth. Missing files throw an
// Error that says which files to get, from where, and where they go.
LpipsFiles find_lpips_files(LpipsBackbone backbone, const std::filesystem::path& dir = {});

class LpipsImpl : public torch::nn::Module {
 public:
  explicit LpipsImpl(LpipsBackbone backbone);
  // {B,3,H,W} images in [0,1] each (H, W >= 32 for AlexNet's strides) -> {B} distances, in fp32.
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& y);
  // The five normalised-free backbone feature maps of images already in [-1,1] (for tests).
  std::vector<torch::Tensor> features(const torch::Tensor& x);
  LpipsBackbone backbone() const { return backbone_; }

 private:
  LpipsBackbone backbone_;
  torch::nn::Sequential features_{nullptr};  // torchvision's `features`, indices as there
  std::vector<size_t> taps_;                 // indices of the ReLUs whose outputs LPIPS compares
  std::vector<torch::Tensor> linear_;        // lin0..lin4: {1,C,1,1}
};
TORCH_MODULE(Lpips);

// Loads both files into a frozen model in eval mode. Errors name the file and the tensor (missing,
// wrong shape, NaN); a file that is not torch.save's is refused by the reader, naming it.
Lpips load_lpips(LpipsBackbone backbone, const LpipsFiles& files);

}  // namespace flatnet
