#include "nn/generator.hpp"

#include "optics/separable_inverse.hpp"

#include "core/error.hpp"
#include "core/precision.hpp"
#include "nn/onednn_conv.hpp"

namespace flatnet {

namespace nn = torch::nn;

// ---- Inversion -----------------------------------------------------------------------------------

FlatInversionImpl::FlatInversionImpl(const InversionOptions& o) : negative_slope_(o.negative_slope) {
  TORCH_CHECK(o.phil.dim() == 3 && o.phir.dim() == 3 && o.phil.size(1) == o.phir.size(1) &&
                  o.phil.size(2) == o.phir.size(2) && (o.phil.size(2) == 1 || o.phil.size(2) == 4),
              "inversion: PhiL {rows,N,k} and PhiR {cols,N,k} with k 1 or 4 expected, got ", o.phil.sizes(), " and ",
              o.phir.sizes());
  PhiL = register_parameter("PhiL", o.phil.to(torch::kFloat32).clone());
  PhiR = register_parameter("PhiR", o.phir.to(torch::kFloat32).clone());
}

namespace {

// L^T Y R for {k,rows,n} L, {4,rows,cols} Y, {k,cols,m} R (k = 1 or 4): through oneDNN's GEMM where
// the tensors allow it (CPU, fp32), which runs these skinny products about twice as fast as OpenBLAS
// in fp32 (`flatnet bench --rows train_recipe --profile 20`); torch::matmul otherwise. With bf16
// operands, Y, the weights and Y R are rounded to bf16 as they enter each product; both products
// accumulate and return fp32, so the first stage's output keeps fp32's resolution.
torch::Tensor first_stage_product(const torch::Tensor& L, const torch::Tensor& Y, const torch::Tensor& R,
                                  GemmOperands operands) {
  const bool onednn = Y.is_cpu() && Y.scalar_type() == torch::kFloat32 && L.scalar_type() == torch::kFloat32 &&
                      R.scalar_type() == torch::kFloat32 && Y.dim() == 3;
  if (!onednn) return torch::matmul(L.transpose(1, 2), torch::matmul(Y, R));
  const auto YR = onednn_matmul_autograd(Y, R, operands);          // {4,rows,m}
  return onednn_matmul_autograd(L.transpose(1, 2), YR, operands);  // {4,n,m}
}

}  // namespace

torch::Tensor FlatInversionImpl::forward(const torch::Tensor& Y) {
  // Y {B,4,rows,cols}. Weights as {k,rows,N} / {k,cols,N}; k = 1 broadcasts over the channels.
  const auto L = PhiL.permute({2, 0, 1});  // {k,rows,N}
  const auto R = PhiR.permute({2, 0, 1});  // {k,cols,N}
  torch::Tensor X;                         // {B,4,N,N}
  if (Y.dim() == 4) {                      // one sample at a time, so that each product can go through oneDNN
    std::vector<torch::Tensor> samples;
    for (int64_t b = 0; b < Y.size(0); ++b) samples.push_back(first_stage_product(L, Y[b], R, operands_));
    X = torch::stack(samples);
  } else {
    X = first_stage_product(L, Y, R, operands_);
  }
  return torch::leaky_relu(X, negative_slope_).flip({1});  // (b,gb,gr,r) -> (r,gr,gb,b)
}

torch::Tensor FlatInversionImpl::forward_crops(const torch::Tensor& Y,
                                               const std::vector<std::pair<int64_t, int64_t>>& corners, int64_t size) {
  TORCH_CHECK(static_cast<int64_t>(corners.size()) == Y.size(0), "inversion: one crop corner per sample expected");
  const auto L = PhiL.permute({2, 0, 1}), R = PhiR.permute({2, 0, 1});  // {k,rows,N}, {k,cols,N}
  std::vector<torch::Tensor> out;
  for (int64_t b = 0; b < Y.size(0); ++b) {
    const auto [r0, c0] = corners[b];
    // Rows r0..r0+size of X = L^T Y R need only those columns of L (and likewise for R).
    const auto Lb = L.slice(2, r0, r0 + size), Rb = R.slice(2, c0, c0 + size);  // {k,rows,s}, {k,cols,s}
    out.push_back(first_stage_product(Lb, Y[b], Rb, operands_));                // {4,s,s}
  }
  return torch::leaky_relu(torch::stack(out), negative_slope_).flip({1});
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
  torch::NoGradGuard no_grad;
  const auto inverse = separable_inverse(P, Q, lambda);  // thesis eq. 2.6
  ULt_.copy_(inverse.ULt);
  UR_.copy_(inverse.UR);
  VL_.copy_(inverse.VL);
  VRt_.copy_(inverse.VRt);
  filter_.copy_(inverse.filter);
}

torch::Tensor TikhonovLayerImpl::forward(const torch::Tensor& Y) {
  return apply_separable_inverse(ULt_, UR_, VL_, VRt_, filter_, Y).flip({1});  // {B,4,N,N}, (r, gr, gb, b)
}

// ---- Generator -----------------------------------------------------------------------------------

MeasurementPreprocessorImpl::MeasurementPreprocessorImpl(const PreprocessorOptions& o)
    : negative_slope_(o.negative_slope), convs_(register_module("convs", nn::ModuleList())) {
  TORCH_CHECK(o.width >= 1 && o.depth >= 2, "pre-processor: width >= 1 and depth >= 2 expected, got ", o.width, ", ",
              o.depth);
  for (int64_t i = 0; i < o.depth; ++i) {
    const int64_t in = i == 0 ? 4 : o.width, out = i + 1 == o.depth ? 4 : o.width;
    convs_->push_back(nn::Conv2d(nn::Conv2dOptions(in, out, 3).padding(1).bias(false)));
  }
  torch::NoGradGuard no_grad;
  convs_->ptr<nn::Conv2dImpl>(o.depth - 1)->weight.zero_();  // g = 0: the identity at the start
}

torch::Tensor MeasurementPreprocessorImpl::forward(const torch::Tensor& Y) {  // {B,4,rows,cols}
  // Channels-last: with 4 to `width` channels over 310,000 pixels, the default layout runs these
  // convolutions 3-4x slower (measured with Python torch 1.13, one thread, batch 8, width 8).
  auto h = Y.contiguous(at::MemoryFormat::ChannelsLast);
  const auto n = convs_->size();
  for (size_t i = 0; i < n; ++i) {
    h = convs_->ptr<nn::Conv2dImpl>(i)->forward(h);  // {B,width,rows,cols}, the last {B,4,rows,cols}
    if (i + 1 < n) h = torch::leaky_relu(h, negative_slope_);
  }
  return Y + h.contiguous();
}

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
    case Enhancer::unet:
      enhancer_ = nn::AnyModule(register_module("enhancer", UNet(o.unet)));
      break;
    case Enhancer::dncnn:
      enhancer_ = nn::AnyModule(register_module("enhancer", DnCNN(o.dncnn)));
      break;
    case Enhancer::rcan:
      enhancer_ = nn::AnyModule(register_module("enhancer", RCAN(o.rcan)));
      break;
    case Enhancer::nafnet:
      enhancer_ = nn::AnyModule(register_module("enhancer", NAFNet(o.nafnet)));
      break;
  }
  // Registered last, so the other parameters keep their order with or without it.
  if (o.preprocessor.width > 0)
    preprocessor_ = register_module("preprocessor", MeasurementPreprocessor(o.preprocessor));
}

void GeneratorImpl::check_measurement(const torch::Tensor& Y) const {
  TORCH_CHECK(Y.dim() == 4 && Y.size(1) == 4 && Y.size(2) == options_.rows && Y.size(3) == options_.cols,
              "generator: measurement planes {B,4,", options_.rows, ",", options_.cols, "} expected, got ", Y.sizes());
}

void check_camera_for_model(const GeneratorOptions& go, const CameraConfig& camera) {
  if (camera.raw.crop[2] != go.rows || camera.raw.crop[3] != go.cols || camera.scene_size != go.scene)
    throw Error("camera '" + camera.name + "': its crop " + std::to_string(camera.raw.crop[2]) + "x" +
                std::to_string(camera.raw.crop[3]) + " and scene " + std::to_string(camera.scene_size) +
                " do not match the model's " + std::to_string(go.rows) + "x" + std::to_string(go.cols) + " and " +
                std::to_string(go.scene));
  const bool level = camera.raw.centring == Centring::level;
  if (go.level_input && !level)
    throw Error("camera '" + camera.name +
                "': the model reads the light level (model.level_input) but the camera's centring is '" +
                centring_name(camera.raw.centring) + "'; use a camera file with `centring: level`");
  if (!go.level_input && level)
    throw Error("camera '" + camera.name +
                "': centring 'level' keeps the light level in the planes, which this model does not "
                "read (model.level_input is off); use `centring: plane`");
}

std::pair<torch::Tensor, torch::Tensor> GeneratorImpl::split_level(const torch::Tensor& Y) const {
  if (!options_.level_input) return {Y, torch::Tensor()};
  const auto level = Y.mean({2, 3}, true);  // {B,4,1,1}, planes in (b, gb, gr, r) order
  return {Y - level, level.flip({1})};      // the first stage's order (r, gr, gb, b)
}

torch::Tensor GeneratorImpl::first_stage_of(const torch::Tensor& planes) {
  return inversion_ ? inversion_->forward(planes) : tikhonov_->forward(planes);
}

torch::Tensor GeneratorImpl::preprocessed(const torch::Tensor& planes) {
  return preprocessor_ ? preprocessor_->forward(planes) : planes;
}

torch::Tensor GeneratorImpl::first_stage(const torch::Tensor& Y) {
  check_measurement(Y);
  return first_stage_of(preprocessed(split_level(Y).first));
}

torch::Tensor GeneratorImpl::forward(const torch::Tensor& Y) {
  check_measurement(Y);
  const auto [planes, level] = split_level(Y);
  return enhance(first_stage_of(preprocessed(planes)), level);
}

torch::Tensor GeneratorImpl::forward_crops(const torch::Tensor& Y,
                                           const std::vector<std::pair<int64_t, int64_t>>& corners, int64_t size) {
  TORCH_CHECK(size >= 16 && size % 16 == 0 && size <= options_.scene,
              "generator: crop size must be a multiple of 16 in [16, ", options_.scene, "], got ", size);
  for (const auto& [r, c] : corners)
    TORCH_CHECK(r >= 0 && c >= 0 && r + size <= options_.scene && c + size <= options_.scene, "generator: crop at (", r,
                ",", c, ") leaves the ", options_.scene, "x", options_.scene, " scene");
  check_measurement(Y);
  const auto [raw_planes, level] = split_level(Y);
  const auto planes = preprocessed(raw_planes);  // the whole capture: each window sees all of it
  if (inversion_) return enhance(inversion_->forward_crops(planes, corners, size), level);
  return enhance(crop_windows(first_stage_of(planes), corners, size), level);
}

torch::Tensor crop_windows(const torch::Tensor& images, const std::vector<std::pair<int64_t, int64_t>>& corners,
                           int64_t size) {
  if (corners.empty()) return images;
  std::vector<torch::Tensor> out;
  for (size_t b = 0; b < corners.size(); ++b)
    out.push_back(images[b]
                      .slice(1, corners[b].first, corners[b].first + size)
                      .slice(2, corners[b].second, corners[b].second + size));
  return torch::stack(out);
}

torch::Tensor GeneratorImpl::enhance(const torch::Tensor& first, const torch::Tensor& level) {
  torch::Tensor y;
  {
    // bf16 autocast covers BN and the enhancer only; the first stage ran in fp32 before it.
    AutocastGuard autocast(autocast_bf16_ && !levers_.bf16);
    const Bf16KernelScope bf16_kernels(levers_.bf16);  // bf16 weights: kernels that run them here
    auto x = bn_->forward(first);                      // {B,4,H,W}
    if (level.defined())                               // {B,8,H,W}: the level as four constant channels
      x = torch::cat({x, level.to(x.scalar_type()).expand({-1, -1, x.size(2), x.size(3)})}, 1);
    if (levers_.self_ensemble && !is_training()) return self_ensemble(x);
    if (levers_.channels_last) x = x.contiguous(at::MemoryFormat::ChannelsLast);
    if (levers_.bf16) x = x.to(torch::kBFloat16);
    y = enhancer_.forward<torch::Tensor>(x);  // {B,3,H,W} logits
  }
  if (!levers_.bf16 && !levers_.channels_last && y.scalar_type() == torch::kFloat32) return torch::sigmoid(y);
  return torch::sigmoid(y.to(torch::kFloat32)).contiguous();  // the sigmoid (and any loss after it) in fp32
}

torch::Tensor flip_ensemble(const std::function<torch::Tensor(const torch::Tensor&)>& f, const torch::Tensor& x) {
  const std::vector<std::vector<int64_t>> flips = {{}, {3}, {2}, {2, 3}};  // identity, horizontal, vertical, both
  std::vector<torch::Tensor> views;
  for (const auto& dims : flips) views.push_back(dims.empty() ? x : torch::flip(x, dims));
  const auto parts = f(torch::cat(views, 0)).chunk(static_cast<int64_t>(flips.size()), 0);  // 4 x {B,C',H,W}
  auto sum = parts[0].contiguous();
  for (size_t i = 1; i < flips.size(); ++i) sum = sum + torch::flip(parts[i], flips[i]);  // each flip undone
  return sum / static_cast<double>(flips.size());
}

torch::Tensor GeneratorImpl::self_ensemble(const torch::Tensor& x) {  // {B,C,H,W} -> {B,3,H,W} in [0,1]
  // The level channels are constant over the image, so the flips leave them as they are.
  return flip_ensemble(
             [this](const torch::Tensor& batch) {  // {4B,C,H,W}
               auto in = levers_.channels_last ? batch.contiguous(at::MemoryFormat::ChannelsLast) : batch;
               if (levers_.bf16) in = in.to(torch::kBFloat16);
               return torch::sigmoid(
                   enhancer_.forward<torch::Tensor>(in).to(torch::kFloat32));  // images, then averaged
             },
             x)
      .contiguous();
}

void GeneratorImpl::prepare_training(const InferenceLevers& levers) {
  auto l = levers;
  l.fold_batchnorm = false;  // batch statistics are needed while training
  l.bf16 = false;            // bf16 training is autocast (fp32 master weights), see set_autocast_bf16
  apply_levers(l, false);
}

void GeneratorImpl::set_autocast_bf16(bool on) {
  autocast_bf16_ = on;
  if (on) use_bf16_kernels_for_process();
  if (inversion_)
    inversion_->set_product_operands(on && cpu_features().native_bf16() ? GemmOperands::bf16 : GemmOperands::fp32);
}

void GeneratorImpl::prepare_inference(const InferenceLevers& levers) {
  eval();
  apply_levers(levers, true);
}

void GeneratorImpl::apply_levers(const InferenceLevers& levers, bool for_inference) {
  // The U-Net's levers are its own (DnCNN, RCAN and NAFNet take bf16 and channels-last only).
  const auto unet = std::dynamic_pointer_cast<UNetImpl>(named_children()["enhancer"]);
  if (unet && levers.fold_batchnorm && !levers_.fold_batchnorm) unet->fold_batchnorm();
  if (unet) unet->set_upsampling(levers.gemm_upsample, for_inference);
  auto& enhancer = *named_children()["enhancer"];
  torch::NoGradGuard no_grad;
  if (levers.bf16) enhancer.to(torch::kBFloat16);
  auto folded = levers;  // batch norm folded by this call or an earlier one
  folded.fold_batchnorm = levers.fold_batchnorm || levers_.fold_batchnorm;
  if (unet && for_inference && folded.onednn_active()) unet->use_onednn();
  if (levers.channels_last) weights_to_channels_last(enhancer);
  levers_.fold_batchnorm = levers_.fold_batchnorm || levers.fold_batchnorm;
  levers_.channels_last = levers.channels_last;
  levers_.bf16 = levers.bf16;
  levers_.self_ensemble = for_inference && levers.self_ensemble;
}

void weights_to_channels_last(torch::nn::Module& module) {
  torch::NoGradGuard no_grad;
  for (auto& p : module.parameters())
    if (p.dim() == 4) p.set_data(p.contiguous(at::MemoryFormat::ChannelsLast));
}

bool InferenceLevers::onednn_active() const { return onednn && bf16 && fold_batchnorm && cpu_features().onednn_bf16; }

InferenceLevers parse_inference_levers(const std::string& s) {
  InferenceLevers l{false, false, false, false, false};
  if (s == "none" || s.empty()) return l;
  std::stringstream in(s);
  std::string item;
  while (std::getline(in, item, ',')) {
    if (item == "fold")
      l.fold_batchnorm = true;
    else if (item == "channels-last")
      l.channels_last = true;
    else if (item == "bf16")
      l.bf16 = true;
    else if (item == "gemm-up")
      l.gemm_upsample = true;
    else if (item == "onednn")
      l.onednn = true;
    else
      throw Error(option_key("infer.levers") +
                  ": expected none or a list of fold, channels-last, gemm-up, bf16, onednn; got '" + item + "'");
  }
  return l;
}

std::string inference_levers_text(const InferenceLevers& l) {
  std::string text;
  for (const auto& [on, name] :
       {std::pair{l.fold_batchnorm, "fold"}, std::pair{l.channels_last, "channels-last"},
        std::pair{l.gemm_upsample, "gemm-up"}, std::pair{l.bf16, "bf16"}, std::pair{l.onednn, "onednn"}})
    if (on) text += (text.empty() ? "" : ",") + std::string(name);
  return text.empty() ? "none" : text;
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
  if (s == "nafnet") return Enhancer::nafnet;
  throw Error("config: model.enhancer must be unet, dncnn, rcan or nafnet, got '" + s + "'");
}

}  // namespace flatnet
