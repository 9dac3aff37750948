#include "nn/lpips.hpp"

#include <cstdlib>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/torch_file.hpp"

namespace flatnet {

namespace nn = torch::nn;

namespace {

// torchvision's layer lists: a conv is {out, kernel, stride, padding}, a max pool is kernel 0 (its
// size and stride follow the network: 3/2 for AlexNet, 2/2 for VGG). ReLUs follow every conv.
struct ConvSpec {
  int64_t out, kernel, stride, padding;
};
const ConvSpec kPool{0, 0, 0, 0};

// torchvision.models.alexnet().features[0:12] (the last max pool is not used by LPIPS).
const std::vector<ConvSpec> kAlexNet = {{64, 11, 4, 2}, kPool,          {192, 5, 1, 2}, kPool,
                                        {384, 3, 1, 1}, {256, 3, 1, 1}, {256, 3, 1, 1}};
// torchvision.models.vgg16().features[0:30] (cfg "D" without its last pool).
const std::vector<ConvSpec> kVgg16 = {{64, 3, 1, 1},  {64, 3, 1, 1},  kPool,          {128, 3, 1, 1}, {128, 3, 1, 1},
                                      kPool,          {256, 3, 1, 1}, {256, 3, 1, 1}, {256, 3, 1, 1}, kPool,
                                      {512, 3, 1, 1}, {512, 3, 1, 1}, {512, 3, 1, 1}, kPool,          {512, 3, 1, 1},
                                      {512, 3, 1, 1}, {512, 3, 1, 1}};

// The ReLUs LPIPS taps, as indices into `features` (lpips/pretrained_networks.py's slices):
// AlexNet relu1..relu5, VGG-16 relu1_2, relu2_2, relu3_3, relu4_3, relu5_3.
const std::vector<size_t> kAlexTaps = {1, 4, 7, 9, 11};
const std::vector<size_t> kVggTaps = {3, 8, 15, 22, 29};

std::filesystem::path torch_hub_checkpoints() {
  if (const char* home = std::getenv("TORCH_HOME"); home && *home)
    return std::filesystem::path(home) / "hub" / "checkpoints";
  if (const char* xdg = std::getenv("XDG_CACHE_HOME"); xdg && *xdg)
    return std::filesystem::path(xdg) / "torch" / "hub" / "checkpoints";
  if (const char* home = std::getenv("HOME"); home && *home)
    return std::filesystem::path(home) / ".cache" / "torch" / "hub" / "checkpoints";
  return {};
}

// The first regular file in `dir` whose name starts with `prefix` and ends with ".pth", by name.
std::filesystem::path first_match(const std::filesystem::path& dir, const std::string& prefix) {
  std::error_code ec;
  if (dir.empty() || !std::filesystem::is_directory(dir, ec)) return {};
  std::vector<std::filesystem::path> found;
  for (const auto& e : std::filesystem::directory_iterator(dir, ec)) {
    const auto name = e.path().filename().string();
    if (e.is_regular_file(ec) && name.rfind(prefix, 0) == 0 && e.path().extension() == ".pth")
      found.push_back(e.path());
  }
  std::sort(found.begin(), found.end());
  return found.empty() ? std::filesystem::path() : found.front();
}

torch::Tensor checked_tensor(const PyValue& dict, const std::string& key, const std::vector<int64_t>& shape,
                             const std::filesystem::path& file, const std::string& what) {
  const auto value = dict.get(key);
  require(value && value->kind == PyValue::Kind::tensor, file, "missing tensor '" + key + "' (" + what + ")");
  require(value->tensor.sizes() == c10::IntArrayRef(shape), file,
          "tensor '" + key + "' has the wrong shape for " + what + ": " + value->describe() + ", expected " +
              c10::str(c10::IntArrayRef(shape)));
  require(torch::isfinite(value->tensor).all().item<bool>(), file, "tensor '" + key + "' holds NaN or infinity");
  return value->tensor;
}

PyRef read_state_dict(const std::filesystem::path& file, const std::string& what) {
  require(std::filesystem::is_regular_file(file), file, "not found (" + what + ")");
  const auto root = read_torch_file(file);  // zip or legacy torch.save; refuses code, names the file
  require(root->is_dict(), file, "expected a state dict of " + what + ", found a " + root->describe());
  return root;
}

}  // namespace

LpipsBackbone parse_lpips_backbone(const std::string& name) {
  if (name == "alex") return LpipsBackbone::alex;
  if (name == "vgg") return LpipsBackbone::vgg;
  throw Error("LPIPS backbone: expected alex or vgg, got '" + name + "'");
}

std::string lpips_backbone_name(LpipsBackbone backbone) { return backbone == LpipsBackbone::alex ? "alex" : "vgg"; }

LpipsFiles find_lpips_files(LpipsBackbone backbone, const std::filesystem::path& dir) {
  const bool alex = backbone == LpipsBackbone::alex;
  const std::string prefix = alex ? "alexnet-" : "vgg16-", linear_name = alex ? "alex.pth" : "vgg.pth";
  std::vector<std::filesystem::path> dirs;
  if (!dir.empty()) dirs.push_back(dir);
  dirs.push_back(data_dir() / "models" / "lpips");
  if (const auto hub = torch_hub_checkpoints(); !hub.empty()) dirs.push_back(hub);
  LpipsFiles files;
  for (const auto& d : dirs) {
    if (files.backbone.empty()) files.backbone = first_match(d, prefix);
    std::error_code ec;
    if (files.linear.empty() && std::filesystem::is_regular_file(d / linear_name, ec)) files.linear = d / linear_name;
  }
  if (!files.backbone.empty() && !files.linear.empty()) return files;
  std::string where;
  for (const auto& d : dirs) where += (where.empty() ? "" : ", ") + d.string();
  throw Error(dirs.front(), "LPIPS (" + lpips_backbone_name(backbone) + ") needs two files, " +
                                (files.backbone.empty() ? "missing " : "found ") + "torchvision's " + prefix +
                                "*.pth (" + (alex ? "alexnet-owt-7be5be79.pth" : "vgg16-397923af.pth") +
                                ", from download.pytorch.org/models/) and " +
                                (files.linear.empty() ? "missing " : "found ") + "the lpips package's " + linear_name +
                                " (lpips/weights/v0.1/ in pip's lpips or github.com/richzhang/PerceptualSimilarity); "
                                "put them in one of: " +
                                where);
}

LpipsImpl::LpipsImpl(LpipsBackbone backbone) : backbone_(backbone) {
  const bool alex = backbone == LpipsBackbone::alex;
  features_ = nn::Sequential();
  int64_t in = 3;
  for (const auto& c : alex ? kAlexNet : kVgg16) {
    if (c.out == 0) {
      features_->push_back(nn::MaxPool2d(nn::MaxPool2dOptions(alex ? 3 : 2).stride(2)));
    } else {
      features_->push_back(nn::Conv2d(nn::Conv2dOptions(in, c.out, c.kernel).stride(c.stride).padding(c.padding)));
      features_->push_back(nn::ReLU());
      in = c.out;
    }
  }
  register_module("features", features_);
  taps_ = alex ? kAlexTaps : kVggTaps;
  for (size_t l = 0; l < taps_.size(); ++l) {
    const auto channels = features_[taps_[l] - 1]->as<nn::Conv2dImpl>()->options.out_channels();
    linear_.push_back(register_parameter("lin" + std::to_string(l), torch::zeros({1, channels, 1, 1})));
  }
  for (auto& p : parameters()) p.set_requires_grad(false);
}

std::vector<torch::Tensor> LpipsImpl::features(const torch::Tensor& x) {
  std::vector<torch::Tensor> out;
  auto h = x;
  for (size_t i = 0; i <= taps_.back(); ++i) {
    if (auto conv = features_[i]->as<nn::Conv2dImpl>())
      h = conv->forward(h);
    else if (features_[i]->as<nn::ReLUImpl>())
      h = torch::relu(h);
    else
      h = features_[i]->as<nn::MaxPool2dImpl>()->forward(h);
    if (std::find(taps_.begin(), taps_.end(), i) != taps_.end()) out.push_back(h);
  }
  return out;
}

torch::Tensor LpipsImpl::forward(const torch::Tensor& x, const torch::Tensor& y) {
  TORCH_CHECK(x.dim() == 4 && x.size(1) == 3 && x.sizes() == y.sizes(), "LPIPS takes two {B,3,H,W} images of one size");
  const auto shift = torch::tensor({-.030f, -.088f, -.188f}).view({1, 3, 1, 1});
  const auto scale = torch::tensor({.458f, .448f, .450f}).view({1, 3, 1, 1});
  auto prepare = [&](const torch::Tensor& t) { return ((t.to(torch::kFloat) * 2 - 1) - shift) / scale; };
  const auto fx = features(prepare(x)), fy = features(prepare(y));
  auto unit = [](const torch::Tensor& f) { return f / (f.pow(2).sum(1, true).sqrt() + 1e-10); };
  torch::Tensor d = torch::zeros({x.size(0)});
  for (size_t l = 0; l < fx.size(); ++l) {
    const auto diff = (unit(fx[l]) - unit(fy[l])).pow(2);     // {B,C,h,w}
    d = d + torch::conv2d(diff, linear_[l]).mean({1, 2, 3});  // 1x1 conv, spatial mean
  }
  return d;
}

Lpips load_lpips(LpipsBackbone backbone, const LpipsFiles& files) {
  const std::string name = lpips_backbone_name(backbone);
  const std::string net = backbone == LpipsBackbone::alex ? "AlexNet" : "VGG-16";
  Lpips model(backbone);
  torch::NoGradGuard no_grad;
  const auto trunk = read_state_dict(files.backbone, "torchvision's " + net);
  const auto linear = read_state_dict(files.linear, "LPIPS " + name + " linear layers");
  for (auto& p : model->named_parameters()) {
    const auto& key = p.key();
    if (key.rfind("features.", 0) == 0) {
      // torchvision's whole-model state dict: "features.N.weight"; a saved `features` alone: "N.weight".
      const auto short_key = key.substr(std::string("features.").size());
      const auto& from = trunk->get(key) ? key : short_key;
      p.value().copy_(checked_tensor(*trunk, from, p.value().sizes().vec(), files.backbone, net + "'s " + key));
    } else {  // lin0 ... lin4, the package's NetLinLayer: Dropout (index 0) then the 1x1 conv (index 1)
      const auto lin_key = key + ".model.1.weight";
      p.value().copy_(checked_tensor(*linear, lin_key, p.value().sizes().vec(), files.linear,
                                     "LPIPS " + name + " v0.1's linear layer"));
    }
  }
  model->eval();
  return model;
}

}  // namespace flatnet
