#include "nn/enhancers.hpp"

#include "core/error.hpp"
#include "core/precision.hpp"
#include "nn/onednn_conv.hpp"

namespace flatnet {

namespace nn = torch::nn;

// ---- U-Net building blocks, named as FlatNet's models.py ----------------------------------------

namespace {

// Eval-mode batch norm folded into the convolution before it (inference only):
//   BN(W*x + b) = s (W*x + b - mean) + beta,  s = gamma / sqrt(var + eps)
//   => W' = s W (per output channel), b' = s (b - mean) + beta.
// ReLUs become in-place; other modules are kept as they are.
nn::Sequential fold_sequential(nn::Sequential seq) {
  nn::Sequential out;
  torch::NoGradGuard no_grad;
  const std::vector<nn::AnyModule> items(seq->begin(), seq->end());
  for (size_t i = 0; i < items.size(); ++i) {
    auto conv = seq[i]->as<nn::Conv2dImpl>();
    auto bn = i + 1 < items.size() ? seq[i + 1]->as<nn::BatchNorm2dImpl>() : nullptr;
    if (conv && bn) {
      const auto& co = conv->options;
      auto folded = nn::Conv2d(nn::Conv2dOptions(co.in_channels(), co.out_channels(), co.kernel_size())
                                   .stride(co.stride())
                                   .padding(co.padding())
                                   .dilation(co.dilation())
                                   .groups(co.groups())
                                   .bias(true));
      const auto s = bn->weight / torch::sqrt(bn->running_var + bn->options.eps());
      folded->weight.copy_(conv->weight * s.view({-1, 1, 1, 1}));
      const auto b = conv->bias.defined() ? conv->bias : torch::zeros_like(bn->running_mean);
      folded->bias.copy_(s * (b - bn->running_mean) + bn->bias);
      out->push_back(folded);
      ++i;
    } else if (seq[i]->as<nn::ReLUImpl>()) {
      out->push_back(nn::ReLU(nn::ReLUOptions().inplace(true)));
    } else {
      out->push_back(items[i]);
    }
  }
  return out;
}

// (conv3x3 => BN => ReLU) x 2; the first conv may have stride 2 (FlatNet's double_conv2).
struct DoubleConvImpl : nn::Module {
  DoubleConvImpl(int64_t in, int64_t out, int64_t stride, double momentum) {
    conv = register_module(
        "conv",
        nn::Sequential(nn::Conv2d(nn::Conv2dOptions(in, out, 3).stride(stride).padding(1)),
                       nn::BatchNorm2d(nn::BatchNormOptions(out).momentum(momentum)),
                       nn::ReLU(nn::ReLUOptions().inplace(true)),  // as FlatNet (BN's backward needs its input only)
                       nn::Conv2d(nn::Conv2dOptions(out, out, 3).padding(1)),
                       nn::BatchNorm2d(nn::BatchNormOptions(out).momentum(momentum)),
                       nn::ReLU(nn::ReLUOptions().inplace(true))));
  }
  torch::Tensor forward(const torch::Tensor& x) {
    if (!fused.empty()) return (*fused[1])((*fused[0])(x));  // conv+bias+ReLU twice, in oneDNN
    if (!is_training() || conv->size() != 6) return conv->forward(x);
    // Training: each batch norm and its ReLU as one oneDNN primitive where it runs.
    auto h = convolve(*conv[0]->as<nn::Conv2dImpl>(), x);
    h = batch_norm_activation(*conv[1]->as<nn::BatchNorm2dImpl>(), h, NormActivation::relu);
    h = convolve(*conv[3]->as<nn::Conv2dImpl>(), h);
    return batch_norm_activation(*conv[4]->as<nn::BatchNorm2dImpl>(), h, NormActivation::relu);
  }
  void fold_batchnorm() { conv = replace_module("conv", fold_sequential(conv)); }
  // After fold_batchnorm (conv, ReLU, conv, ReLU): both convolutions with their ReLUs fused, run by
  // oneDNN directly with prepacked weights (bf16 inference; see nn/onednn_conv.hpp).
  void use_onednn() {
    for (size_t i : {0, 2}) {
      const auto c = conv[i]->as<nn::Conv2dImpl>();
      TORCH_CHECK(c && conv[i + 1]->as<nn::ReLUImpl>(), "use_onednn: fold the batch norm first");
      OneDnnConvOptions o;
      o.stride = c->options.stride()->at(0),
      o.padding = c10::get<torch::ExpandingArray<2>>(c->options.padding())->at(0);
      o.relu = true;
      fused.push_back(std::make_shared<OneDnnConv>(c->weight, c->bias, o));
    }
  }
  nn::Sequential conv{nullptr};
  std::vector<std::shared_ptr<OneDnnConv>> fused;
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
    const auto cl = at::MemoryFormat::ChannelsLast;
    if (gemm_up && cache_weights && deep.is_contiguous(cl) && skip.is_contiguous(cl) &&
        skip.size(2) == 2 * deep.size(2) && skip.size(3) == 2 * deep.size(3))
      return conv->forward(upsample_into_concat(deep, skip));
    auto x1 = gemm_up ? upsample_as_gemm(deep) : up->forward(deep);
    auto x2 = skip;
    const int64_t dy = x1.size(2) - x2.size(2), dx = x1.size(3) - x2.size(3);
    if (dy != 0 || dx != 0) x2 = torch::constant_pad_nd(x2, {dx / 2, dx - dx / 2, dy / 2, dy - dy / 2});
    return conv->forward(cat_channels(x2, x1));
  }
  // Inference: the upsampled map is written straight into its half of the concatenation (one
  // strided copy of runs of O values moves each output pixel into place: no separate bias pass,
  // permute copy or cat).
  torch::Tensor upsample_into_concat(const torch::Tensor& x, const torch::Tensor& skip) {  // {B,C,H,W}, {B,S,2H,2W}
    const int64_t B = x.size(0), H = x.size(2), W = x.size(3), O = up->weight.size(1), S = skip.size(1);
    const auto y = upsample_columns(x).permute({0, 1, 3, 2, 4, 5});  // [b][i][di][j][dj][o]
    auto out = concat_buffer(skip, O, x.scalar_type());
    out.narrow(1, S, O).permute({0, 2, 3, 1}).view({B, H, 2, W, 2, O}).copy_(y);
    return out;
  }
  // torch::cat along the channels of channels-last maps takes a slow path in LibTorch 1.13 (10 ms
  // for 2 x 128 channels at 256x256 in bf16, 22 ms in fp32); two slice copies into a channels-last
  // buffer give the same tensor in 1.7 ms. ConcatChannelsLast carries the gradient.
  static torch::Tensor cat_channels(const torch::Tensor& a, const torch::Tensor& b) {
    const auto cl = at::MemoryFormat::ChannelsLast;
    if (!a.is_contiguous(cl) || !b.is_contiguous(cl) || a.dim() != 4) return torch::cat({a, b}, 1);
    return ConcatChannelsLast::apply(a, b);
  }
  // Its own backward, because autograd's through two slice copies (CopySlices) copies the whole
  // gradient of the buffer once per slice, and in LibTorch 1.13 that copy came out in the
  // channels-first order, so every later use paid a transposing copy (one U-Net training step in
  // bf16 spent ~0.7 s on them at 256x256). Here each input's gradient is its slice of the
  // buffer's, copied once, channels-last.
  struct ConcatChannelsLast : torch::autograd::Function<ConcatChannelsLast> {
    static torch::Tensor forward(torch::autograd::AutogradContext* ctx, const torch::Tensor& a,
                                 const torch::Tensor& b) {
      ctx->saved_data["split"] = a.size(1);
      ctx->saved_data["a_type"] = a.scalar_type();
      ctx->saved_data["b_type"] = b.scalar_type();
      auto out = concat_buffer(a, b.size(1), b.scalar_type());  // {B,Ca+Cb,H,W}
      out.narrow(1, a.size(1), b.size(1)).copy_(b);
      return out;
    }
    static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                   torch::autograd::variable_list grads) {
      const auto cl = at::MemoryFormat::ChannelsLast;
      const int64_t split = ctx->saved_data["split"].toInt();
      const auto& g = grads[0];
      auto slice = [&](int64_t from, int64_t n, const char* type) {
        return g.narrow(1, from, n).to(ctx->saved_data[type].toScalarType()).contiguous(cl);
      };
      return {slice(0, split, "a_type"), slice(split, g.size(1) - split, "b_type")};
    }
  };
  // A channels-last {B, C + extra, H, W} buffer (the promoted type of `first` and `other`) whose
  // first C channels are `first`; the caller fills the rest.
  static torch::Tensor concat_buffer(const torch::Tensor& first, int64_t extra, at::ScalarType other) {
    auto out = torch::empty({first.size(0), first.size(1) + extra, first.size(2), first.size(3)},
                            first.options()
                                .dtype(at::promote_types(first.scalar_type(), other))
                                .memory_format(at::MemoryFormat::ChannelsLast));
    out.narrow(1, 0, first.size(1)).copy_(first);
    return out;
  }
  // The 2x2, stride-2 transposed convolution as one GEMM (exact: output pixels do not overlap):
  //   out[b, o, 2i+di, 2j+dj] = sum_c x[b, c, i, j] W[c, o, di, dj] + bias[o].
  // In NHWC, X {B*H*W, C} @ W {C, 4*O} then an interleaving copy; LibTorch 1.13's own CPU kernel
  // (slow_conv_transpose2d: im2col and NCHW only) is 2-3x slower here.
  torch::Tensor upsample_as_gemm(const torch::Tensor& x) {  // {B,C,H,W} -> {B,O,2H,2W}
    const int64_t B = x.size(0), H = x.size(2), W = x.size(3), O = up->weight.size(1);
    // -> [b][i][di][j][dj][o]: NHWC of the upsampled map, then viewed as channels_last NCHW.
    return upsample_columns(x)
        .permute({0, 1, 3, 2, 4, 5})
        .contiguous()
        .view({B, 2 * H, 2 * W, O})
        .permute({0, 3, 1, 2});
  }
  // The GEMM, {B,H,W,2,2,O} ([b][i][j][di][dj][o]). Its columns are ordered [di][dj][o], so the
  // interleaving copies move runs of O contiguous values (ordered [o][di][dj] they moved pairs: 4x
  // slower in bf16 training), and the bias rides in it (addmm), one value per column.
  torch::Tensor upsample_columns(const torch::Tensor& x) {
    const int64_t B = x.size(0), C = x.size(1), H = x.size(2), W = x.size(3), O = up->weight.size(1);
    const auto type = x.scalar_type();
    torch::Tensor w, bias;
    if (!cache_weights) {  // training and validation: the live parameters (gradients reach them; never stale)
      w = up->weight.permute({0, 2, 3, 1}).reshape({C, 4 * O}).to(type);  // a view for channels-last fp32 weights
      bias = up->bias.repeat({4}).to(type);
    } else {  // a module prepared for inference (weights frozen): reordered (and cast) once
      if (!gemm_weight.defined() || gemm_weight.scalar_type() != type) {
        gemm_weight = up->weight.detach().permute({0, 2, 3, 1}).reshape({C, 4 * O}).to(type).contiguous();
        gemm_bias = up->bias.detach().repeat({4}).to(type);
      }
      w = gemm_weight;
      bias = gemm_bias;
    }
    return torch::addmm(bias, x.permute({0, 2, 3, 1}).reshape({B * H * W, C}), w).view({B, H, W, 2, 2, O});
  }
  nn::ConvTranspose2d up{nullptr};
  DoubleConv conv{nullptr};
  bool gemm_up = false;
  // Only after prepare_inference: the weights no longer change, so their GEMM layout is kept. A
  // cache while training would be a stale copy after the first optimiser step (channels-last
  // weights reshape to a copy, not a view).
  bool cache_weights = false;
  torch::Tensor gemm_weight, gemm_bias;  // cached for inference: {C,4*O} [c][di][dj][o], {4*O}
};
TORCH_MODULE(Up);

struct OutConvImpl : nn::Module {
  OutConvImpl(int64_t in, int64_t out) {
    conv = register_module("conv", nn::Conv2d(nn::Conv2dOptions(in, out, 3).padding(1)));
  }
  torch::Tensor forward(const torch::Tensor& x) { return fused ? (*fused)(x) : convolve(*conv, x); }
  void use_onednn() {
    OneDnnConvOptions o;
    o.padding = 1;
    fused = std::make_shared<OneDnnConv>(conv->weight, conv->bias, o);
  }
  nn::Conv2d conv{nullptr};
  std::shared_ptr<OneDnnConv> fused;
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

void UNetImpl::fold_batchnorm() {
  for (auto& m : modules(/*include_self=*/false))
    if (auto dc = std::dynamic_pointer_cast<DoubleConvImpl>(m)) dc->fold_batchnorm();
}

void UNetImpl::set_upsampling(bool gemm, bool cache_weights) {
  for (auto& up : ups_) {
    auto u = std::static_pointer_cast<UpImpl>(up);
    u->gemm_up = gemm;
    u->cache_weights = cache_weights;
    u->gemm_weight = u->gemm_bias = torch::Tensor();
  }
}

void UNetImpl::use_onednn() {
  for (auto& m : modules(/*include_self=*/false)) {
    if (auto dc = std::dynamic_pointer_cast<DoubleConvImpl>(m)) dc->use_onednn();
    if (auto oc = std::dynamic_pointer_cast<OutConvImpl>(m)) oc->use_onednn();
  }
}

torch::Tensor UNetImpl::forward(const torch::Tensor& x) {
  const auto x1 = inc_.forward(x);     // {B,w,H,W}
  const auto x2 = down1_.forward(x1);  // {B,2w,H/2,W/2}
  const auto x3 = down2_.forward(x2);  // {B,4w,H/4,W/4}
  const auto x4 = down3_.forward(x3);  // {B,8w,H/8,W/8}
  const auto x5 = down4_.forward(x4);  // {B,8w,H/16,W/16}
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

// ---- NAFNet --------------------------------------------------------------------------------------

LayerNorm2dImpl::LayerNorm2dImpl(int64_t channels) {
  weight = register_parameter("weight", torch::ones({channels}));
  bias = register_parameter("bias", torch::zeros({channels}));
}

torch::Tensor LayerNorm2dImpl::forward(const torch::Tensor& x) {
  const auto mean = x.mean(1, true);
  const auto centred = x - mean;
  const auto var = centred.pow(2).mean(1, true);
  return centred * torch::rsqrt(var + 1e-6) * weight.view({1, -1, 1, 1}) + bias.view({1, -1, 1, 1});
}

namespace {

// SimpleGate: the first half of the channels times the second.  {B,2c,H,W} -> {B,c,H,W}
torch::Tensor simple_gate(const torch::Tensor& x) {
  const auto halves = x.chunk(2, 1);
  return halves[0] * halves[1];
}

struct NAFBlockImpl : nn::Module {
  explicit NAFBlockImpl(int64_t c) {
    conv1 = register_module("conv1", nn::Conv2d(nn::Conv2dOptions(c, 2 * c, 1)));
    conv2 = register_module("conv2", nn::Conv2d(nn::Conv2dOptions(2 * c, 2 * c, 3).padding(1).groups(2 * c)));
    conv3 = register_module("conv3", nn::Conv2d(nn::Conv2dOptions(c, c, 1)));
    sca = register_module("sca", nn::Sequential(nn::AdaptiveAvgPool2d(1), nn::Conv2d(nn::Conv2dOptions(c, c, 1))));
    conv4 = register_module("conv4", nn::Conv2d(nn::Conv2dOptions(c, 2 * c, 1)));
    conv5 = register_module("conv5", nn::Conv2d(nn::Conv2dOptions(c, c, 1)));
    norm1 = register_module("norm1", LayerNorm2d(c));
    norm2 = register_module("norm2", LayerNorm2d(c));
    beta = register_parameter("beta", torch::zeros({1, c, 1, 1}));
    gamma = register_parameter("gamma", torch::zeros({1, c, 1, 1}));
  }
  torch::Tensor forward(const torch::Tensor& in) {                             // {B,c,H,W}
    auto x = simple_gate(conv2->forward(conv1->forward(norm1->forward(in))));  // {B,c,H,W}
    x = conv3->forward(x * sca->forward(x));
    const auto y = in + x * beta;
    x = conv5->forward(simple_gate(conv4->forward(norm2->forward(y))));
    return y + x * gamma;
  }
  nn::Conv2d conv1{nullptr}, conv2{nullptr}, conv3{nullptr}, conv4{nullptr}, conv5{nullptr};
  nn::Sequential sca{nullptr};
  LayerNorm2d norm1{nullptr}, norm2{nullptr};
  torch::Tensor beta, gamma;
};
TORCH_MODULE(NAFBlock);

nn::Sequential naf_blocks(int64_t channels, int64_t count) {
  nn::Sequential s;
  for (int64_t i = 0; i < count; ++i) s->push_back(NAFBlock(channels));
  return s;
}

}  // namespace

NAFNetImpl::NAFNetImpl(const NAFNetOptions& o) {
  intro_ = register_module("intro", nn::Conv2d(nn::Conv2dOptions(o.in_channels, o.width, 3).padding(1)));
  encoders_ = register_module("encoders", nn::ModuleList());
  downs_ = register_module("downs", nn::ModuleList());
  ups_ = register_module("ups", nn::ModuleList());
  decoders_ = register_module("decoders", nn::ModuleList());
  int64_t c = o.width;
  for (int level = 0; level < 4; ++level, c *= 2) {
    encoders_->push_back(naf_blocks(c, o.enc_blocks));
    downs_->push_back(nn::Conv2d(nn::Conv2dOptions(c, 2 * c, 2).stride(2)));
  }
  middle_ = register_module("middle_blks", naf_blocks(c, o.middle_blocks));
  for (int level = 0; level < 4; ++level, c /= 2) {
    ups_->push_back(nn::Sequential(nn::Conv2d(nn::Conv2dOptions(c, 2 * c, 1).bias(false)), nn::PixelShuffle(2)));
    decoders_->push_back(naf_blocks(c / 2, o.dec_blocks));
  }
  ending_ = register_module("ending", nn::Conv2d(nn::Conv2dOptions(o.width, o.out_channels, 3).padding(1)));
}

torch::Tensor NAFNetImpl::forward(const torch::Tensor& input) {
  TORCH_CHECK(input.size(2) % 16 == 0 && input.size(3) % 16 == 0, "NAFNet: H and W must be multiples of 16, got ",
              input.sizes());
  auto x = intro_->forward(input);  // {B,w,H,W}
  std::vector<torch::Tensor> skips;
  for (size_t i = 0; i < encoders_->size(); ++i) {
    x = encoders_[i]->as<nn::SequentialImpl>()->forward(x);
    skips.push_back(x);
    x = downs_[i]->as<nn::Conv2dImpl>()->forward(x);  // {B,2c,H/2,W/2}
  }
  x = middle_->forward(x);  // {B,16w,H/16,W/16}
  for (size_t i = 0; i < decoders_->size(); ++i) {
    x = ups_[i]->as<nn::SequentialImpl>()->forward(x) + skips[skips.size() - 1 - i];
    x = decoders_[i]->as<nn::SequentialImpl>()->forward(x);
  }
  return ending_->forward(x);  // {B,out,H,W}
}

}  // namespace flatnet
