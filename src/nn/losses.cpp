#include "nn/losses.hpp"

#include "core/precision.hpp"

#include <fstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/torch_file.hpp"

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

torch::Tensor DiscriminatorImpl::forward(const torch::Tensor& x) {
  auto h = x;
  for (size_t i = 0; i < convs_->size(); ++i) {
    h = norms_[i]->as<nn::BatchNorm2dImpl>()->forward(convs_[i]->as<nn::Conv2dImpl>()->forward(h));
    h = h * torch::sigmoid(h);  // swish
  }
  return out_->forward(h).mean({2, 3});  // {B,1}
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
    h = features_[i]->as<nn::Conv2dImpl>() ? features_[i]->as<nn::Conv2dImpl>()->forward(h)
        : features_[i]->as<nn::ReLUImpl>() ? torch::relu_(h)  // in place, as torchvision's VGG
                                           : features_[i]->as<nn::MaxPool2dImpl>()->forward(h);
    if (i == 8) relu2_2 = h;
  }
  return {relu2_2, h};
}

Vgg16Features load_vgg16(const std::filesystem::path& weights, bool normalize) {
  if (weights.empty() || !std::filesystem::exists(weights))
    throw Error(weights.empty() ? std::filesystem::path("loss.vgg_file") : weights,
                "VGG-16 weights not found; the perceptual loss needs them. Make the file with "
                "`python3 models/convert_vgg16.py` where torchvision can download its weights (or point "
                "loss.vgg_file at torchvision's own vgg16-397923af.pth), or train without the perceptual loss: "
                "--set loss.perceptual=0");
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

}  // namespace flatnet
