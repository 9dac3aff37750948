#include "nn/generator.hpp"

#include "core/error.hpp"

namespace flatnet {

namespace nn = torch::nn;

// ---- Inversion -----------------------------------------------------------------------------------

FlatInversionImpl::FlatInversionImpl(const InversionOptions& o) : negative_slope_(o.negative_slope) {
  TORCH_CHECK(o.phil.dim() == 3 && o.phir.dim() == 3 && o.phil.size(1) == o.phir.size(1) &&
                  o.phil.size(2) == o.phir.size(2) && (o.phil.size(2) == 1 || o.phil.size(2) == 4),
              "inversion: PhiL {rows,N,k} and PhiR {cols,N,k} with k 1 or 4 expected, got ", o.phil.sizes(),
              " and ", o.phir.sizes());
  PhiL = register_parameter("PhiL", o.phil.to(torch::kFloat32).clone());
  PhiR = register_parameter("PhiR", o.phir.to(torch::kFloat32).clone());
}

torch::Tensor FlatInversionImpl::forward(const torch::Tensor& Y) {
  // Y {B,4,rows,cols}. Weights as {k,rows,N} / {k,cols,N}; k = 1 broadcasts over the channels.
  const auto L = PhiL.permute({2, 0, 1});                      // {k,rows,N}
  const auto R = PhiR.permute({2, 0, 1});                      // {k,cols,N}
  const auto X = torch::matmul(L.transpose(1, 2), torch::matmul(Y, R));  // {B,4,N,N}
  return torch::leaky_relu(X, negative_slope_).flip({1});     // (b,gb,gr,r) -> (r,gr,gb,b)
}

// ---- Tikhonov layer ------------------------------------------------------------------------------

TikhonovLayerImpl::TikhonovLayerImpl(int64_t rows, int64_t cols, int64_t n) {
  ULt_ = register_buffer("ULt", torch::zeros({4, n, rows}));
  UR_ = register_buffer("UR", torch::zeros({4, cols, n}));
  VL_ = register_buffer("VL", torch::zeros({4, n, n}));
  VRt_ = register_buffer("VRt", torch::zeros({4, n, n}));
  filter_ = register_buffer("filter", torch::zeros({4, n, n}));
}

TikhonovLayerImpl::TikhonovLayerImpl(const torch::Tensor& P, const torch::Tensor& Q, double lambda)
    : TikhonovLayerImpl(P.size(1), Q.size(1), P.size(2)) {
  // Eq. 2.6: X = V_L [ (s_L s_R^T) / ((s_L s_R^T)^2 + lambda) o (U_L^T Y U_R) ] V_R^T.
  torch::NoGradGuard no_grad;
  auto [UL, sL, VLt] = torch::linalg::svd(P.to(torch::kFloat64), false, c10::nullopt);
  auto [UR, sR, VRt] = torch::linalg::svd(Q.to(torch::kFloat64), false, c10::nullopt);
  const auto s = sL.unsqueeze(2) * sR.unsqueeze(1);  // {4,N,N}
  ULt_.copy_(UL.transpose(1, 2));
  UR_.copy_(UR);
  VL_.copy_(VLt.transpose(1, 2));
  VRt_.copy_(VRt);
  filter_.copy_(s / (s * s + lambda));
}

torch::Tensor TikhonovLayerImpl::forward(const torch::Tensor& Y) {
  const auto core = torch::matmul(ULt_, torch::matmul(Y, UR_)) * filter_;  // {B,4,N,N}
  return torch::matmul(VL_, torch::matmul(core, VRt_)).flip({1});
}

// ---- U-Net building blocks, named as FlatNet's models.py ----------------------------------------

namespace {

// (conv3x3 => BN => ReLU) x 2; the first conv may have stride 2 (FlatNet's double_conv2).
struct DoubleConvImpl : nn::Module {
  DoubleConvImpl(int64_t in, int64_t out, int64_t stride, double momentum) {
    conv = register_module(
        "conv", nn::Sequential(nn::Conv2d(nn::Conv2dOptions(in, out, 3).stride(stride).padding(1)),
                               nn::BatchNorm2d(nn::BatchNormOptions(out).momentum(momentum)), nn::ReLU(),
                               nn::Conv2d(nn::Conv2dOptions(out, out, 3).padding(1)),
                               nn::BatchNorm2d(nn::BatchNormOptions(out).momentum(momentum)), nn::ReLU()));
  }
  torch::Tensor forward(const torch::Tensor& x) { return conv->forward(x); }
  nn::Sequential conv{nullptr};
};
TORCH_MODULE(DoubleConv);

struct InConvImpl : nn::Module {  // FlatNet's inconv
  InConvImpl(int64_t in, int64_t out, double m) { conv = register_module("conv", DoubleConv(in, out, 1, m)); }
  torch::Tensor forward(const torch::Tensor& x) { return conv->forward(x); }
  DoubleConv conv{nullptr};
};
TORCH_MODULE(InConv);

struct DownImpl : nn::Module {  // FlatNet's down: stride-2 double conv
  DownImpl(int64_t in, int64_t out, double m) {
    mpconv = register_module("mpconv", nn::Sequential(DoubleConv(in, out, 2, m)));
  }
  torch::Tensor forward(const torch::Tensor& x) { return mpconv->forward(x); }
  nn::Sequential mpconv{nullptr};
};
TORCH_MODULE(Down);

struct UpImpl : nn::Module {  // FlatNet's up: transposed conv on the deeper map, concat skip, double conv
  UpImpl(int64_t in, int64_t out, double m) {
    up = register_module("up", nn::ConvTranspose2d(nn::ConvTranspose2dOptions(in / 2, in / 2, 2).stride(2)));
    conv = register_module("conv", DoubleConv(in, out, 1, m));
  }
  torch::Tensor forward(const torch::Tensor& deep, const torch::Tensor& skip) {
    auto x1 = up->forward(deep);
    auto x2 = skip;
    const int64_t dy = x1.size(2) - x2.size(2), dx = x1.size(3) - x2.size(3);
    if (dy != 0 || dx != 0) x2 = torch::constant_pad_nd(x2, {dx / 2, dx - dx / 2, dy / 2, dy - dy / 2});
    return conv->forward(torch::cat({x2, x1}, 1));
  }
  nn::ConvTranspose2d up{nullptr};
  DoubleConv conv{nullptr};
};
TORCH_MODULE(Up);

struct OutConvImpl : nn::Module {
  OutConvImpl(int64_t in, int64_t out) { conv = register_module("conv", nn::Conv2d(nn::Conv2dOptions(in, out, 3).padding(1))); }
  torch::Tensor forward(const torch::Tensor& x) { return conv->forward(x); }
  nn::Conv2d conv{nullptr};
};
TORCH_MODULE(OutConv);

}  // namespace

UNetImpl::UNetImpl(const UNetOptions& o) {
  const int64_t w = o.width;
  const double m = o.bn_momentum;
  TORCH_CHECK(w >= 1, "unet: width must be positive");
  inc_ = nn::AnyModule(register_module("inc", InConv(o.in_channels, w, m)));
  down1_ = nn::AnyModule(register_module("down1", Down(w, 2 * w, m)));
  down2_ = nn::AnyModule(register_module("down2", Down(2 * w, 4 * w, m)));
  down3_ = nn::AnyModule(register_module("down3", Down(4 * w, 8 * w, m)));
  down4_ = nn::AnyModule(register_module("down4", Down(8 * w, 8 * w, m)));
  ups_.push_back(register_module("up1", Up(16 * w, 4 * w, m)));
  ups_.push_back(register_module("up2", Up(8 * w, 2 * w, m)));
  ups_.push_back(register_module("up3", Up(4 * w, w, m)));
  ups_.push_back(register_module("up4", Up(2 * w, w, m)));
  outc_ = nn::AnyModule(register_module("outc", OutConv(w, o.out_channels)));
}

torch::Tensor UNetImpl::forward(const torch::Tensor& x) {
  const auto x1 = inc_.forward(x);    // {B,w,H,W}
  const auto x2 = down1_.forward(x1); // {B,2w,H/2,W/2}
  const auto x3 = down2_.forward(x2); // {B,4w,H/4,W/4}
  const auto x4 = down3_.forward(x3); // {B,8w,H/8,W/8}
  const auto x5 = down4_.forward(x4); // {B,8w,H/16,W/16}
  auto up = [&](int i, const torch::Tensor& deep, const torch::Tensor& skip) {
    return std::static_pointer_cast<UpImpl>(ups_[i])->forward(deep, skip);
  };
  auto y = up(0, x5, x4);  // {B,4w,H/8,W/8}
  y = up(1, y, x3);        // {B,2w,H/4,W/4}
  y = up(2, y, x2);        // {B,w,H/2,W/2}
  y = up(3, y, x1);        // {B,w,H,W}
  return outc_.forward(y);
}

// ---- DnCNN ---------------------------------------------------------------------------------------

DnCNNImpl::DnCNNImpl(const DnCNNOptions& o) {
  TORCH_CHECK(o.layers >= 3, "dncnn: at least 3 layers");
  body_ = nn::Sequential();
  body_->push_back(nn::Conv2d(nn::Conv2dOptions(o.in_channels, o.width, 3).padding(1)));
  body_->push_back(nn::ReLU());
  for (int64_t i = 0; i < o.layers - 2; ++i) {
    body_->push_back(nn::Conv2d(nn::Conv2dOptions(o.width, o.width, 3).padding(1).bias(false)));
    body_->push_back(nn::BatchNorm2d(nn::BatchNormOptions(o.width).momentum(o.bn_momentum)));
    body_->push_back(nn::ReLU());
  }
  body_->push_back(nn::Conv2d(nn::Conv2dOptions(o.width, o.out_channels, 3).padding(1)));
  register_module("body", body_);
}

torch::Tensor DnCNNImpl::forward(const torch::Tensor& x) { return body_->forward(x); }

// ---- RCAN ----------------------------------------------------------------------------------------

namespace {

// Residual channel-attention block: x + CA(conv(relu(conv(x)))).
struct RCABImpl : nn::Module {
  RCABImpl(int64_t w, int64_t reduction) {
    const int64_t squeezed = std::max<int64_t>(1, w / reduction);
    conv1 = register_module("conv1", nn::Conv2d(nn::Conv2dOptions(w, w, 3).padding(1)));
    conv2 = register_module("conv2", nn::Conv2d(nn::Conv2dOptions(w, w, 3).padding(1)));
    squeeze = register_module("squeeze", nn::Conv2d(nn::Conv2dOptions(w, squeezed, 1)));
    excite = register_module("excite", nn::Conv2d(nn::Conv2dOptions(squeezed, w, 1)));
  }
  torch::Tensor forward(const torch::Tensor& x) {
    auto r = conv2->forward(torch::relu(conv1->forward(x)));
    auto a = torch::sigmoid(excite->forward(torch::relu(squeeze->forward(r.mean({2, 3}, true)))));
    return x + r * a;
  }
  nn::Conv2d conv1{nullptr}, conv2{nullptr}, squeeze{nullptr}, excite{nullptr};
};
TORCH_MODULE(RCAB);

struct ResidualGroupImpl : nn::Module {
  ResidualGroupImpl(int64_t blocks, int64_t w, int64_t reduction) {
    body = register_module("body", nn::Sequential());
    for (int64_t i = 0; i < blocks; ++i) body->push_back(RCAB(w, reduction));
    body->push_back(nn::Conv2d(nn::Conv2dOptions(w, w, 3).padding(1)));
  }
  torch::Tensor forward(const torch::Tensor& x) { return x + body->forward(x); }
  nn::Sequential body{nullptr};
};
TORCH_MODULE(ResidualGroup);

}  // namespace

RCANImpl::RCANImpl(const RCANOptions& o) {
  head_ = register_module("head", nn::Conv2d(nn::Conv2dOptions(o.in_channels, o.width, 3).padding(1)));
  groups_ = register_module("groups", nn::ModuleList());
  for (int64_t g = 0; g < o.groups; ++g) groups_->push_back(ResidualGroup(o.blocks, o.width, o.reduction));
  body_end_ = register_module("body_end", nn::Conv2d(nn::Conv2dOptions(o.width, o.width, 3).padding(1)));
  tail_ = register_module("tail", nn::Conv2d(nn::Conv2dOptions(o.width, o.out_channels, 3).padding(1)));
}

torch::Tensor RCANImpl::forward(const torch::Tensor& x) {
  const auto h = head_->forward(x);
  auto y = h;
  for (const auto& g : *groups_) y = g->as<ResidualGroupImpl>()->forward(y);
  y = body_end_->forward(y) + h;
  return tail_->forward(y);
}

// ---- Generator -----------------------------------------------------------------------------------

GeneratorImpl::GeneratorImpl(const GeneratorOptions& o) : options_(o) {
  if (o.input == InputStage::inversion) {
    inversion_ = register_module("inversion", FlatInversion(o.inversion));
  } else if (o.tik_P.defined()) {
    tikhonov_ = register_module("tikhonov", TikhonovLayer(o.tik_P, o.tik_Q, o.tik_lambda));
  } else {
    tikhonov_ = register_module("tikhonov", TikhonovLayer(o.rows, o.cols, o.scene));
  }
  bn_ = register_module("bn", nn::BatchNorm2d(nn::BatchNormOptions(4).momentum(o.bn_momentum)));
  switch (o.enhancer) {
    case Enhancer::unet: enhancer_ = nn::AnyModule(register_module("enhancer", UNet(o.unet))); break;
    case Enhancer::dncnn: enhancer_ = nn::AnyModule(register_module("enhancer", DnCNN(o.dncnn))); break;
    case Enhancer::rcan: enhancer_ = nn::AnyModule(register_module("enhancer", RCAN(o.rcan))); break;
  }
}

torch::Tensor GeneratorImpl::first_stage(const torch::Tensor& Y) {
  TORCH_CHECK(Y.dim() == 4 && Y.size(1) == 4 && Y.size(2) == options_.rows && Y.size(3) == options_.cols,
              "generator: measurement planes {B,4,", options_.rows, ",", options_.cols, "} expected, got ",
              Y.sizes());
  return inversion_ ? inversion_->forward(Y) : tikhonov_->forward(Y);
}

torch::Tensor GeneratorImpl::forward(const torch::Tensor& Y) {
  const auto x = bn_->forward(first_stage(Y));          // {B,4,N,N}
  return torch::sigmoid(enhancer_.forward<torch::Tensor>(x));  // {B,3,N,N}
}

InputStage parse_input_stage(const std::string& s) {
  if (s == "inversion") return InputStage::inversion;
  if (s == "tikhonov") return InputStage::tikhonov;
  throw Error("config: model.input must be inversion or tikhonov, got '" + s + "'");
}

Enhancer parse_enhancer(const std::string& s) {
  if (s == "unet") return Enhancer::unet;
  if (s == "dncnn") return Enhancer::dncnn;
  if (s == "rcan") return Enhancer::rcan;
  throw Error("config: model.enhancer must be unet, dncnn or rcan, got '" + s + "'");
}

}  // namespace flatnet
