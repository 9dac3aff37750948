#include "nn/losses.hpp"

#include "core/precision.hpp"

#include <fstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/torch_file.hpp"
#include "nn/onednn_conv.hpp"

namespace flatnet {

namespace nn = torch::nn;

DiscriminatorImpl::DiscriminatorImpl(const DiscriminatorOptions& o) {
  const bool flatnet = o.kind == "flatnet";
  if (!flatnet && o.kind != "thesis")
    throw Error("config: discriminator.kind must be thesis or flatnet, got '" + o.kind + "'");
  const int layers = flatnet ? 3 : 4;
  convs_ = register_module("convs", nn::ModuleList());
  norms_ = register_module("norms", nn::ModuleList());
  int64_t in = 3, w = o.width;
  for (int i = 0; i < layers; ++i, in = w, w *= 2) {
    convs_->push_back(nn::Conv2d(nn::Conv2dOptions(in, w, 3).stride(2).padding(1)));
    norms_->push_back(nn::BatchNorm2d(w));
  }
  out_ = register_module("out", nn::Conv2d(nn::Conv2dOptions(in, 1, 1).padding(flatnet ? 1 : 0)));
}

torch::Tensor DiscriminatorImpl::forward(const torch::Tensor& x) { return features(x).back(); }

std::vector<torch::Tensor> DiscriminatorImpl::features(const torch::Tensor& x) {
  std::vector<torch::Tensor> out;
  // The input follows the weights' layout (weights_to_channels_last): an NCHW image into NHWC weights
  // sends every convolution and its gradients through oneDNN's reorders (2-3x the backward's time).
  const auto& first = convs_[0]->as<nn::Conv2dImpl>()->weight;
  const bool channels_last = first.is_contiguous(at::MemoryFormat::ChannelsLast) && !first.is_contiguous();
  auto h = channels_last ? x.contiguous(at::MemoryFormat::ChannelsLast) : x;
  for (size_t i = 0; i < convs_->size(); ++i) {
    h = batch_norm_activation(*norms_[i]->as<nn::BatchNorm2dImpl>(), convolve(*convs_[i]->as<nn::Conv2dImpl>(), h),
                              NormActivation::swish);
    out.push_back(h);
  }
  out.push_back(convolve(*out_, h).mean({2, 3}));  // {B,1}
  return out;
}

Vgg16FeaturesImpl::Vgg16FeaturesImpl(bool normalize) : normalize_(normalize) {
  // torchvision cfg "D" up to relu4_3: 64 64 M 128 128 M 256 256 256 M 512 512 512
  const std::vector<int64_t> cfg = {64, 64, -1, 128, 128, -1, 256, 256, 256, -1, 512, 512, 512};
  features_ = nn::Sequential();
  int64_t in = 3;
  for (const auto c : cfg) {
    if (c < 0) {
      features_->push_back(nn::MaxPool2d(nn::MaxPool2dOptions(2).stride(2)));
    } else {
      features_->push_back(nn::Conv2d(nn::Conv2dOptions(in, c, 3).padding(1)));
      features_->push_back(nn::ReLU());
      in = c;
    }
  }
  register_module("features", features_);  // 23 modules: indices 0..22
  for (auto& p : parameters()) p.set_requires_grad(false);
}

std::pair<torch::Tensor, torch::Tensor> Vgg16FeaturesImpl::forward(const torch::Tensor& x) {
  auto h = x;
  if (normalize_) {
    const auto mean = torch::tensor({0.485f, 0.456f, 0.406f}).view({1, 3, 1, 1});
    const auto std = torch::tensor({0.229f, 0.224f, 0.225f}).view({1, 3, 1, 1});
    h = (h - mean) / std;
  }
  torch::Tensor relu2_2;
  for (size_t i = 0; i < features_->size(); ++i) {
    h = features_[i]->as<nn::Conv2dImpl>() ? convolve(*features_[i]->as<nn::Conv2dImpl>(), h)
        : features_[i]->as<nn::ReLUImpl>() ? torch::relu_(h)  // in place, as torchvision's VGG
                                           : features_[i]->as<nn::MaxPool2dImpl>()->forward(h);
    if (i == 8) relu2_2 = h;
  }
  return {relu2_2, h};
}

Vgg16Features load_vgg16(const std::filesystem::path& weights, bool normalize) {
  if (weights.empty() || !std::filesystem::exists(weights))
    throw Error(weights.empty() ? std::filesystem::path("(no VGG-16 weights file named)") : weights,
                "VGG-16 weights not found; the perceptual loss needs them. Make the file with "
                "`python3 models/convert_vgg16.py` where torchvision can download its weights (or point "
                "loss.vgg_file at torchvision's own vgg16-397923af.pth), or train without the perceptual loss: "
                "loss.perceptual = 0");
  const auto root = read_torch_file(weights);  // zip or legacy torch.save; errors name the file
  require(root->is_dict(), weights,
          "expected a dict of VGG-16 tensors (features.N.weight, ...), found a " + root->describe());
  Vgg16Features vgg(normalize);
  torch::NoGradGuard no_grad;
  for (auto& p : vgg->named_parameters()) {
    // convert_vgg16.py and torchvision's whole-model state dict: "features.N.weight" (the
    // classifier's tensors are ignored); torch.save(vgg.features.state_dict()): "N.weight".
    auto value = root->get(p.key());
    if (!value) value = root->get(p.key().substr(std::string("features.").size()));
    require(value && value->kind == PyValue::Kind::tensor, weights,
            "missing tensor '" + p.key() + "' (expected VGG-16's features.0.weight ... features.21.bias)");
    const auto& t = value->tensor;
    require(t.sizes() == p.value().sizes(), weights,
            "tensor '" + p.key() + "' has the wrong shape for VGG-16: " + value->describe() + ", expected " +
                c10::str(p.value().sizes()));
    require(torch::isfinite(t).all().item<bool>(), weights, "tensor '" + p.key() + "' holds NaN or infinity");
    p.value().copy_(t);
  }
  vgg->eval();
  return vgg;
}

torch::Tensor perceptual_loss(Vgg16Features& vgg, const torch::Tensor& x, const torch::Tensor& y, bool bf16) {
  std::pair<torch::Tensor, torch::Tensor> fx, fy;
  {
    AutocastGuard autocast(bf16);
    {
      torch::NoGradGuard no_grad;
      fy = vgg->forward(y);
    }
    fx = vgg->forward(x);
  }
  auto mse = [](const torch::Tensor& a, const torch::Tensor& b) {
    return torch::mse_loss(a.to(torch::kFloat32), b.to(torch::kFloat32));
  };
  return mse(fx.first, fy.first) + mse(fx.second, fy.second);
}

torch::Tensor feature_matching_loss(Discriminator& d, const torch::Tensor& x, const torch::Tensor& y, bool bf16) {
  std::vector<torch::Tensor> fx, fy;
  {
    AutocastGuard autocast(bf16);
    {
      torch::NoGradGuard no_grad;
      fy = d->features(y);
    }
    fx = d->features(x);
  }
  auto loss = torch::zeros({}, torch::kFloat32);
  for (size_t i = 0; i + 1 < fx.size(); ++i)  // the layers' features, not the logits
    loss = loss + torch::l1_loss(fx[i].to(torch::kFloat32), fy[i].to(torch::kFloat32));
  return loss / static_cast<double>(fx.size() - 1);
}

torch::Tensor focal_frequency_loss(const torch::Tensor& x_in, const torch::Tensor& y_in) {
  TORCH_CHECK(x_in.sizes() == y_in.sizes() && x_in.dim() == 4, "focal_frequency_loss: equal {B,C,H,W} inputs expected");
  AutocastOffGuard fp32;
  const auto fx = torch::fft::fft2(x_in.to(torch::kFloat32), c10::nullopt, {-2, -1}, "ortho");
  const auto fy = torch::fft::fft2(y_in.to(torch::kFloat32), c10::nullopt, {-2, -1}, "ortho");
  const auto diff = fx - fy;
  const auto distance = torch::real(diff).pow(2) + torch::imag(diff).pow(2);  // {B,C,H,W}
  torch::Tensor weight;
  {
    torch::NoGradGuard no_grad;
    weight = distance.sqrt();
    const auto peak = std::get<0>(weight.flatten(2).max(-1)).clamp_min(1e-12);  // {B,C}
    weight = weight / peak.unsqueeze(-1).unsqueeze(-1);
  }
  return (weight * distance).mean();
}

torch::Tensor srgb_to_lab(const torch::Tensor& rgb_in) {
  AutocastOffGuard fp32;
  const auto rgb = rgb_in.to(torch::kFloat32).clamp(0, 1);
  // sRGB decoding (IEC 61966-2-1), then linear RGB -> XYZ (D65), each row over the white point.
  const auto linear = torch::where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055).pow(2.4));
  // (the matrix of skimage.color and of sRGB's original specification)
  const auto m = torch::tensor({0.412453f / 0.95047f, 0.357580f / 0.95047f, 0.180423f / 0.95047f,  //
                                0.212671f, 0.715160f, 0.072169f,                                   //
                                0.019334f / 1.08883f, 0.119193f / 1.08883f, 0.950227f / 1.08883f})
                     .view({3, 3});
  const auto xyz = torch::einsum("ij,bjhw->bihw", {m, linear});
  // f(t) = t^(1/3) above (6/29)^3, linear below (finite gradient at black).
  const double d = 6.0 / 29.0;
  const auto f = torch::where(xyz > d * d * d, xyz.clamp_min(d * d * d).pow(1.0 / 3.0), xyz / (3 * d * d) + 4.0 / 29.0);
  const auto fx = f.select(1, 0), fy = f.select(1, 1), fz = f.select(1, 2);
  return torch::stack({116 * fy - 16, 500 * (fx - fy), 200 * (fy - fz)}, 1);
}

torch::Tensor chroma_loss(const torch::Tensor& x, const torch::Tensor& y) {
  const auto lx = srgb_to_lab(x), ly = srgb_to_lab(y.detach());
  return torch::l1_loss(lx.slice(1, 1, 3), ly.slice(1, 1, 3)) / 100.0;
}

torch::Tensor gradient_loss(const torch::Tensor& x_in, const torch::Tensor& y_in) {
  AutocastOffGuard fp32;
  const auto x = x_in.to(torch::kFloat32), y = y_in.to(torch::kFloat32);
  auto dx = [](const torch::Tensor& t) { return t.slice(3, 1) - t.slice(3, 0, -1); };
  auto dy = [](const torch::Tensor& t) { return t.slice(2, 1) - t.slice(2, 0, -1); };
  return 0.5 * (torch::l1_loss(dx(x), dx(y)) + torch::l1_loss(dy(x), dy(y)));
}

torch::Tensor stripe_loss(const torch::Tensor& x_in, const torch::Tensor& y_in) {
  TORCH_CHECK(x_in.sizes() == y_in.sizes() && x_in.dim() == 4, "stripe_loss: equal {B,C,H,W} inputs expected, got ",
              x_in.sizes(), " and ", y_in.sizes());
  AutocastOffGuard fp32;
  // fp32 at least (float64 stays: eval's stripe_energy scores through this).
  const auto type = x_in.scalar_type() == torch::kFloat64 ? torch::kFloat64 : torch::kFloat32;
  const auto error = x_in.to(type) - y_in.to(type);     // {B,C,H,W}
  auto less_trend = [](const torch::Tensor& profile) {  // {B,C,L}
    // Padding not counted: the window shrinks at the ends.
    return profile - torch::avg_pool1d(profile, {15}, {1}, {7}, /*ceil_mode=*/false, /*count_include_pad=*/false);
  };
  const auto rows = less_trend(error.mean(3)), cols = less_trend(error.mean(2));  // {B,C,H}, {B,C,W}
  return (rows.square().sum() + cols.square().sum()) / static_cast<double>(rows.numel() + cols.numel());
}

torch::Tensor psnr_loss(const torch::Tensor& x_in, const torch::Tensor& y_in) {
  TORCH_CHECK(x_in.sizes() == y_in.sizes() && x_in.dim() == 4, "psnr_loss: equal {B,C,H,W} inputs expected, got ",
              x_in.sizes(), " and ", y_in.sizes());
  AutocastOffGuard fp32;
  const auto x = x_in.to(torch::kFloat32), y = y_in.to(torch::kFloat32);
  const auto per_image = (x - y).square().flatten(1).mean(1);  // {B}
  return 10.0 * torch::log10(per_image.clamp_min(1e-10)).mean();
}

torch::Tensor ssim_loss(const torch::Tensor& x_in, const torch::Tensor& y_in) {
  TORCH_CHECK(x_in.sizes() == y_in.sizes() && x_in.dim() == 4 && x_in.size(2) >= 11 && x_in.size(3) >= 11,
              "ssim_loss: equal {B,C,H,W} inputs of at least 11x11 expected, got ", x_in.sizes(), " and ",
              y_in.sizes());
  AutocastOffGuard fp32;
  const auto x = x_in.to(torch::kFloat32), y = y_in.to(torch::kFloat32);
  const int64_t C = x.size(1);
  const double sigma = 1.5;
  auto k = torch::arange(-5, 6, torch::kFloat32);
  k = torch::exp(-0.5 * (k / sigma).pow(2));
  k = k / k.sum();
  const auto kh = k.view({1, 1, 1, 11}).repeat({C, 1, 1, 1}), kv = k.view({1, 1, 11, 1}).repeat({C, 1, 1, 1});
  auto filt = [&](const torch::Tensor& t) {  // separable Gaussian per channel, 'valid'
    namespace F = torch::nn::functional;
    return F::conv2d(F::conv2d(t, kh, F::Conv2dFuncOptions().groups(C)), kv, F::Conv2dFuncOptions().groups(C));
  };
  const auto ux = filt(x), uy = filt(y);
  const auto vx = filt(x * x) - ux * ux, vy = filt(y * y) - uy * uy, vxy = filt(x * y) - ux * uy;
  const double C1 = 0.01 * 0.01, C2 = 0.03 * 0.03;
  const auto s = ((2 * ux * uy + C1) * (2 * vxy + C2)) / ((ux * ux + uy * uy + C1) * (vx + vy + C2));
  return 1 - s.mean();
}

namespace {

// The luma (Rec. 601, as eval's detail measure) of {B,3,H,W} as {B,1,H,W}.
torch::Tensor luma_of(const torch::Tensor& rgb) {
  return (0.299 * rgb.select(1, 0) + 0.587 * rgb.select(1, 1) + 0.114 * rgb.select(1, 2)).unsqueeze(1);
}

// {B,1,H,W} less its 3x3 binomial blur (edges replicated): the band of one pyramid level.
torch::Tensor band_of(const torch::Tensor& luma) {
  namespace F = torch::nn::functional;
  const auto k1 = torch::tensor({0.25f, 0.5f, 0.25f});
  const auto k = (k1.view({3, 1}) * k1.view({1, 3})).view({1, 1, 3, 3});
  const auto padded = F::pad(luma, F::PadFuncOptions({1, 1, 1, 1}).mode(torch::kReplicate));
  return luma - F::conv2d(padded, k);
}

// Mean |band| over 8x8 windows, stride 4: {B,1,H,W} -> {B,1,(H-8)/4+1,(W-8)/4+1}.
torch::Tensor local_energy(const torch::Tensor& band) { return torch::avg_pool2d(band.abs(), {8, 8}, {4, 4}); }

}  // namespace

torch::Tensor detail_energy_loss(const torch::Tensor& x_in, const torch::Tensor& y_in) {
  TORCH_CHECK(
      x_in.sizes() == y_in.sizes() && x_in.dim() == 4 && x_in.size(1) == 3 && x_in.size(2) >= 32 && x_in.size(3) >= 32,
      "detail_energy_loss: equal {B,3,H,W} inputs with H, W >= 32 expected, got ", x_in.sizes(), " and ", y_in.sizes());
  AutocastOffGuard fp32;
  auto lx = luma_of(x_in.to(torch::kFloat32)), ly = luma_of(y_in.detach().to(torch::kFloat32));
  torch::Tensor total = torch::zeros({}, torch::kFloat32);
  const int levels = 3;
  for (int l = 0; l < levels; ++l) {
    if (l > 0) lx = torch::avg_pool2d(lx, 2), ly = torch::avg_pool2d(ly, 2);
    if (lx.size(2) < 8 || lx.size(3) < 8) break;
    total = total + torch::l1_loss(local_energy(band_of(lx)), local_energy(band_of(ly)));
  }
  return total / levels;
}

namespace {

// The fixed random network of random_feature_loss: {out channels} per stage, two convolutions each.
struct RandomFeatureNet {
  std::vector<torch::Tensor> weights;  // {out,in,3,3}, He-normal (std sqrt(2 / (9 in)))
  std::vector<int> stage_end;          // index of each stage's last convolution
};

const RandomFeatureNet& random_feature_net() {
  static const RandomFeatureNet net = [] {
    RandomFeatureNet n;
    auto gen = at::detail::createCPUGenerator(kRandomFeatureSeed);
    int64_t in = 3;
    for (const int64_t c : {16, 32, 64}) {
      for (int i = 0; i < 2; ++i, in = c)
        n.weights.push_back(torch::randn({c, in, 3, 3}, gen, torch::kFloat32) * std::sqrt(2.0 / (9.0 * in)));
      n.stage_end.push_back(static_cast<int>(n.weights.size()) - 1);
    }
    return n;
  }();
  return net;
}

}  // namespace

std::vector<torch::Tensor> random_features(const torch::Tensor& x_in) {
  AutocastOffGuard fp32;
  const auto& net = random_feature_net();
  std::vector<torch::Tensor> out;
  auto h = (x_in.to(torch::kFloat32) - 0.5) * 2.0;  // centred: [0,1] -> [-1,1]
  size_t stage = 0;
  for (size_t i = 0; i < net.weights.size(); ++i) {
    h = torch::relu(torch::conv2d(h, net.weights[i], {}, 1, 1));
    if (static_cast<int>(i) == net.stage_end[stage]) {
      out.push_back(h);
      if (++stage < net.stage_end.size()) h = torch::max_pool2d(h, 2);
    }
  }
  return out;
}

torch::Tensor random_feature_loss(const torch::Tensor& x, const torch::Tensor& y) {
  TORCH_CHECK(x.sizes() == y.sizes() && x.dim() == 4 && x.size(1) == 3,
              "random_feature_loss: equal {B,3,H,W} inputs expected, got ", x.sizes(), " and ", y.sizes());
  const auto fx = random_features(x);
  std::vector<torch::Tensor> fy;
  {
    torch::NoGradGuard no_grad;
    fy = random_features(y);
  }
  torch::Tensor total = torch::zeros({}, torch::kFloat32);
  for (size_t i = 0; i < fx.size(); ++i) total = total + torch::l1_loss(fx[i], fy[i]);
  return total / static_cast<double>(fx.size());
}

}  // namespace flatnet
