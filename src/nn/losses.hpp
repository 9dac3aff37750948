#pragma once
// The adversarial and perceptual parts of FlatNet's loss:
//   L = l1 * MSE(x, y) + l2 * (MSE(vgg_relu2_2) + MSE(vgg_relu4_3)) + l3 * BCE(D(x), 1)
#include <filesystem>
#include <string>

#include <torch/torch.h>

namespace flatnet {

// Discriminator: stride-2 conv3x3 layers, each with batch norm and swish, then a 1x1 conv to one
// channel and a global average: one logit per image (use BCE on logits).
//   thesis:  4 layers, widths w, 2w, 4w, 8w
//   flatnet: 3 layers, widths w, 2w, 4w, final 1x1 conv with padding 1, as FlatNet's models.py
struct DiscriminatorOptions {
  std::string kind = "thesis";  // thesis | flatnet
  int64_t width = 32;
};

class DiscriminatorImpl : public torch::nn::Module {
 public:
  explicit DiscriminatorImpl(const DiscriminatorOptions& options);
  torch::Tensor forward(const torch::Tensor& x);  // {B,3,H,W} -> {B,1} logits
  // The activation after each swish layer ({B,w,H/2,W/2}, {B,2w,H/4,W/4}, ...) and, last, the logits.
  std::vector<torch::Tensor> features(const torch::Tensor& x);

 private:
  torch::nn::ModuleList convs_, norms_;
  torch::nn::Conv2d out_{nullptr};
};
TORCH_MODULE(Discriminator);

// VGG-16 as torchvision's `vgg16().features[0:23]` (parameter names features.N.weight/bias),
// frozen. forward returns relu2_2 (after features[8]) and relu4_3 (after features[22]).
// FlatNet feeds it images in [0,1] without ImageNet normalisation; `normalize` adds it.
class Vgg16FeaturesImpl : public torch::nn::Module {
 public:
  explicit Vgg16FeaturesImpl(bool normalize = false);
  std::pair<torch::Tensor, torch::Tensor> forward(const torch::Tensor& x);  // {B,3,H,W}

 private:
  torch::nn::Sequential features_{nullptr};
  bool normalize_;
};
TORCH_MODULE(Vgg16Features);

// Loads weights written by models/convert_vgg16.py (a torch.save'd dict of features.N.* tensors).
// Errors name the file and, when it is missing, how to make it or train without it.
Vgg16Features load_vgg16(const std::filesystem::path& weights, bool normalize = false);

// Structural loss 1 - SSIM(x, y) (Wang et al. 2004), differentiable: 11x11 Gaussian window with
// sigma 1.5, C1 = 0.01^2, C2 = 0.03^2, 'valid' borders, per channel, averaged. The same definition
// as eval's ssim() (skimage's gaussian_weights=True), so the loss optimises the reported score.
// Computed in fp32 even inside a bf16 autocast region. {B,C,H,W} each, H and W >= 11.
torch::Tensor ssim_loss(const torch::Tensor& x, const torch::Tensor& y);

// Sum of the MSEs of the two VGG feature maps of x and y (y's features need no gradient). With
// `bf16`, VGG runs under bf16 autocast (as the generator's enhancer does when training in bf16) and
// the MSEs in fp32.
torch::Tensor perceptual_loss(Vgg16Features& vgg, const torch::Tensor& x, const torch::Tensor& y, bool bf16 = false);

// Perceptual terms that need no downloaded weights (issue 26). Each takes {B,3,H,W} images in
// [0,1] (the output x and the truth y; y needs no gradient) and is computed in fp32, also inside
// a bf16 autocast region.

// Feature matching (pix2pixHD, Wang et al. 2018, eq. 4): the mean over the discriminator's layers of
// the L1 distance between the features of x and of y. The discriminator's weights get no gradient
// from it (the caller freezes them); x does. With `bf16`, the discriminator runs under autocast.
torch::Tensor feature_matching_loss(Discriminator& d, const torch::Tensor& x, const torch::Tensor& y,
                                    bool bf16 = false);

// Focal frequency loss (Jiang et al., ICCV 2021, eq. 2-4, alpha = 1): the squared distance of the
// orthonormal 2-D spectra, each frequency weighted by its own distance (square root, normalised to
// [0,1] by the image's largest, no gradient), so the frequencies the output misses most count most.
torch::Tensor focal_frequency_loss(const torch::Tensor& x, const torch::Tensor& y);

// CIELAB (D65) of sRGB images: {B,3,H,W} in [0,1] -> {B,3,H,W} with L* in [0,100] and a*, b*.
torch::Tensor srgb_to_lab(const torch::Tensor& rgb);

// Colour term: the mean L1 distance of the chroma coordinates (a*, b*) of x and y, over 100 (so that
// a term of 0.01 is one CIELAB unit). Greens turned grey-brown cost here even where luma is right.
torch::Tensor chroma_loss(const torch::Tensor& x, const torch::Tensor& y);

// Gradient (edge) term: the mean L1 distance of the horizontal and vertical differences of x and
// y, per channel. A blurred edge costs in proportion to the contrast lost, not its square.
torch::Tensor gradient_loss(const torch::Tensor& x, const torch::Tensor& y);

// Stripe term: the mean square of the error image's row means and column means, per channel, each
// less its smooth trend (a centred moving average over 15 samples, the window shrinking at the
// ends). The same profiles as eval's stripe_energy: for one image, stripe_energy = 255 sqrt(this).
// Row and column stripes (an inversion's periodic artefacts) cost here; noise that averages out
// along a row, and a slowly varying error, do not.
torch::Tensor stripe_loss(const torch::Tensor& x, const torch::Tensor& y);

// Detail term (issue 112): the local energy of three bands of the luma, matched, not the bands
// themselves. Band l of a pyramid (l = 0, 1, 2: the luma at full, half and quarter size) is the luma
// less its 3x3 binomial blur; its energy is the mean |band| over 8x8 windows (stride 4). The loss
// is the mean L1 distance of x's and y's energies over the bands. It does not care where inside a
// window the fur's hairs are, only that the window has as much fine structure as the truth's: the
// mean a regressor predicts under uncertainty (smooth) costs here, while MSE rewards it.
// {B,3,H,W}, H and W >= 32; fp32.
torch::Tensor detail_energy_loss(const torch::Tensor& x, const torch::Tensor& y);

// Random-feature perceptual term (issue 112; the "generic perceptual loss" of Liu et al., CVPR 2021:
// an untrained deep network's features already capture structure). A VGG-like network of three
// stages of two 3x3 convolutions and ReLU (16, 32, 64 channels; 2x2 max pooling between), He-normal
// weights drawn from a fixed seed (kRandomFeatureSeed), zero biases, never trained: nothing to
// download or ship. The loss is the mean over the stages of the L1 distance of x's and y's
// features. {B,3,H,W} in [0,1]; fp32.
constexpr uint64_t kRandomFeatureSeed = 112;
torch::Tensor random_feature_loss(const torch::Tensor& x, const torch::Tensor& y);
// The network's features ({B,16,H,W}, {B,32,H/2,W/2}, {B,64,H/4,W/4}), for tests.
std::vector<torch::Tensor> random_features(const torch::Tensor& x);

// PSNR term: minus the batch's mean PSNR in dB (peak 1), -mean_i 10 log10(MSE_i), each image's MSE
// over its own pixels. It is the evaluation's score, so every image counts in decibels: a dim
// scene's small absolute errors weigh as much as a bright scene's large ones, where the pooled MSE
// term gives them a fraction of the gradient (its gradient is the MSE term's scaled per image by
// 4.34 / MSE_i). Negative, and finite for an exact reconstruction (MSE floored at 1e-10, 100 dB).
torch::Tensor psnr_loss(const torch::Tensor& x, const torch::Tensor& y);

}  // namespace flatnet
