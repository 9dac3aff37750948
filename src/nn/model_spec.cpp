#include "nn/model_spec.hpp"

#include <cmath>
#include <iomanip>
#include <regex>
#include <sstream>

#include <yaml-cpp/yaml.h>

#include "core/error.hpp"
#include "core/util.hpp"
#include "optics/camera.hpp"
#include "optics/codes.hpp"

namespace flatnet {

const std::vector<OptionField<ModelSpec>>& model_spec_fields() {
  using S = ModelSpec;
  constexpr double kWidths = 4096, kCounts = 1000;
  static const std::vector<OptionField<S>> fields = {
      {"input", &S::input},
      {"inversion.init", &S::inversion_init},
      {"inversion.shared", &S::inversion_shared},
      {"inversion.channel", &S::inversion_channel},
      {"inversion.slope", &S::inversion_slope, 1e-3, 1e3, "a positive slope (sensor pixels per scene pixel)"},
      {"inversion.seed", &S::inversion_seed},
      {"inversion.lambda", &S::inversion_lambda, 1e-12, 1e6, "a positive regulariser"},
      {"inversion.toeplitz_file", &S::inversion_toeplitz_file},
      // At full measurement size (500x620) each filter is a 1.2 MB plane per capture: 256 is 0.3 GB.
      {"preprocessor.width", &S::preprocessor_width, 0, 256, "0 (none) to 256 filters"},
      {"preprocessor.depth", &S::preprocessor_depth, 2, 64, "2 to 64 convolutions"},
      {"enhancer", &S::enhancer},
      {"level_input", &S::level_input},
      {"bn_momentum", &S::bn_momentum, 0, 1, "0 to 1"},
      {"consistency.strength", &S::consistency_strength, 0, 1000, "0 (none) to 1000"},
      {"consistency.blur", &S::consistency_blur, 0, 64, "0 (none) to 64 scene pixels"},
      {"unet.width", nested_member<&S::unet, &UNetOptions::width, S>(), 1, kWidths, "1 to 4096 filters"},
      {"dncnn.layers", nested_member<&S::dncnn, &DnCNNOptions::layers, S>(), 3, kCounts, "3 to 1000 layers"},
      {"dncnn.width", nested_member<&S::dncnn, &DnCNNOptions::width, S>(), 1, kWidths, "1 to 4096 filters"},
      {"nafnet.width", nested_member<&S::nafnet, &NAFNetOptions::width, S>(), 1, kWidths, "1 to 4096 channels"},
      {"nafnet.enc_blocks", nested_member<&S::nafnet, &NAFNetOptions::enc_blocks, S>(), 0, kCounts, "0 to 1000 blocks"},
      {"nafnet.middle_blocks", nested_member<&S::nafnet, &NAFNetOptions::middle_blocks, S>(), 0, kCounts,
       "0 to 1000 blocks"},
      {"nafnet.dec_blocks", nested_member<&S::nafnet, &NAFNetOptions::dec_blocks, S>(), 0, kCounts, "0 to 1000 blocks"},
      {"rcan.groups", nested_member<&S::rcan, &RCANOptions::groups, S>(), 1, kCounts, "1 to 1000"},
      {"rcan.blocks", nested_member<&S::rcan, &RCANOptions::blocks, S>(), 1, kCounts, "1 to 1000"},
      {"rcan.width", nested_member<&S::rcan, &RCANOptions::width, S>(), 1, kWidths, "1 to 4096 filters"},
      {"rcan.reduction", nested_member<&S::rcan, &RCANOptions::reduction, S>(), 1, kWidths, "1 to 4096"},
  };
  return fields;
}

namespace {

// The spec's settings as dotted keys with their text ("model.unet.width" -> "32").
std::map<std::string, std::string> spec_values(const ModelSpec& spec) {
  std::map<std::string, std::string> out;
  for (const auto& f : model_spec_fields())
    std::visit(
        [&](auto member) {
          auto& text = out[std::string("model.") + f.key];
          if constexpr (std::is_same_v<decltype(member), Choice<ModelSpec>>) {
            if (!member.text) throw std::logic_error("model spec: a row without text cannot be written back");
            text = member.text(spec);  // an enhancer's setting (nested_member)
          } else {
            text = member_text(spec.*member);
          }
        },
        f.member);
  return out;
}

// Initial W1 {rows,N,k}, W2 {cols,N,k} for model.inversion.init.
std::pair<torch::Tensor, torch::Tensor> initial_inversion(const ModelSpec& s, const CameraConfig& camera) {
  const auto& init = s.inversion_init;
  const bool shared = s.inversion_shared;
  const int64_t rows = camera.raw.crop[2], cols = camera.raw.crop[3], n = camera.scene_size;
  const int64_t k = shared ? 1 : 4;
  const auto seed = static_cast<uint64_t>(s.inversion_seed);
  if (init == "transpose") {
    require(!camera.calibration.empty(), "data.camera", "the camera names no calibration (needed for init transpose)");
    const auto calib = load_calibration(camera.calibration, camera);
    if (shared) {
      const int ch = channel_index(s.inversion_channel);
      return {calib.P[ch].unsqueeze(2), calib.Q[ch].unsqueeze(2)};
    }
    return {calib.P.permute({1, 2, 0}), calib.Q.permute({1, 2, 0})};
  }
  if (init == "pinv") {
    require(!camera.calibration.empty(), "data.camera", "the camera names no calibration (needed for init pinv)");
    const double lambda = s.inversion_lambda;
    require(lambda > 0 && std::isfinite(lambda), "model.inversion.lambda", "must be positive");
    const auto calib = load_calibration(camera.calibration, camera);
    // X = W1^T Y W2 with W = U diag(s / (s^2 + lambda s_max^2)) V^T for P = U diag(s) V^T (and Q):
    // each side's Tikhonov-regularised pseudo-inverse, so the first stage starts as a
    // reconstruction rather than the blurred P^T P X Q^T Q of `transpose`.
    auto regularised_pinv = [lambda](const torch::Tensor& M) {  // {m,N} -> {m,N}
      auto [U, S, Vh] = torch::linalg::svd(M.to(torch::kFloat64), false, c10::nullopt);
      const auto smax = S.max();
      return torch::matmul(U * (S / (S * S + lambda * smax * smax)).unsqueeze(-2), Vh).to(torch::kFloat32);
    };
    std::vector<torch::Tensor> L, R;
    const int ch = channel_index(s.inversion_channel);
    for (int64_t i = 0; i < k; ++i) {
      L.push_back(regularised_pinv(calib.P[shared ? ch : i]));
      R.push_back(regularised_pinv(calib.Q[shared ? ch : i]));
    }
    return {torch::stack(L, 2), torch::stack(R, 2)};
  }
  if (init == "calibfree") {
    std::vector<torch::Tensor> L, R;
    for (int64_t i = 0; i < k; ++i) {
      L.push_back(calibration_free_phi(rows, n, s.inversion_slope, seed + 2 * i));
      R.push_back(calibration_free_phi(cols, n, s.inversion_slope, seed + 2 * i + 1));
    }
    return {torch::stack(L, 2), torch::stack(R, 2)};
  }
  if (init == "flatnet-toeplitz") {
    const auto& left = s.inversion_toeplitz_file;
    require(!left.empty(), "model.inversion.toeplitz_file", "must name FlatNet's phil_toep_slope22.mat");
    auto right = left.parent_path() / std::regex_replace(left.filename().string(), std::regex("phil"), "phir");
    auto L = load_flatnet_toeplitz(left, "phil"), R = load_flatnet_toeplitz(right, "phir");  // {4,rows,N}
    require(L.size(1) == rows && R.size(1) == cols && L.size(2) == n, left,
            "Toeplitz matrices do not match the camera's crop and scene size");
    if (shared) return {L[0].unsqueeze(2), R[0].unsqueeze(2)};
    return {L.permute({1, 2, 0}), R.permute({1, 2, 0})};
  }
  if (init == "transfer") {  // filled by transfer_inversion (train --init-from M --reinit inversion)
    return {torch::zeros({rows, n, k}), torch::zeros({cols, n, k})};
  }
  if (init == "random") {
    auto gen = at::detail::createCPUGenerator(seed);
    const double scale = 1.0 / std::sqrt(static_cast<double>(rows));
    return {at::randn({rows, n, k}, gen) * scale, at::randn({cols, n, k}, gen) * scale};
  }
  throw Error(
      "config: model.inversion.init must be transpose, pinv, calibfree, flatnet-toeplitz, random or transfer, got '" +
      init + "'");
}

}  // namespace

ModelSpec model_spec(const Config& config) {
  ModelSpec spec;
  read_options(config, model_spec_fields(), spec, "model.");
  return spec;
}

std::string model_spec_yaml(const ModelSpec& spec) {
  return Config::from_values(spec_values(spec), "model spec").to_yaml();
}

ModelSpec parse_model_spec(const std::string& yaml, const std::filesystem::path& where, bool strict) {
  auto values = spec_values(ModelSpec{});  // a key the text lacks keeps the spec's default
  for (const auto& [key, value] : flat_yaml(yaml, where)) {
    if (key.rfind("model.", 0) != 0) continue;  // an older file's training settings: a record only
    if (!values.count(key)) {
      require(!strict, where, "its model spec has '" + key + "', which this flatnet does not know (a newer file?)");
      continue;  // a key an older config had and the spec dropped
    }
    values[key] = value;
  }
  const auto config = Config::from_values(values, where.string());
  ModelSpec spec;
  read_options(config, model_spec_fields(), spec, "model.");
  return spec;
}

GeneratorOptions generator_options(const ModelSpec& s, const CameraConfig& camera, bool initialise) {
  GeneratorOptions o;
  o.rows = camera.raw.crop[2];
  o.cols = camera.raw.crop[3];
  o.scene = camera.scene_size;
  o.input = parse_input_stage(s.input);
  o.bn_momentum = s.bn_momentum;
  if (o.input == InputStage::inversion) {
    const int64_t k = s.inversion_shared ? 1 : 4;
    if (initialise) {
      std::tie(o.inversion.phil, o.inversion.phir) = initial_inversion(s, camera);
    } else {
      o.inversion.phil = torch::zeros({o.rows, o.scene, k});
      o.inversion.phir = torch::zeros({o.cols, o.scene, k});
    }
  } else if (initialise) {
    require(!camera.calibration.empty(), "data.camera",
            "the camera names no calibration (needed for model.input tikhonov)");
    const auto calib = load_calibration(camera.calibration, camera);
    o.tik_P = calib.P;
    o.tik_Q = calib.Q;
    o.tik_lambda = camera.tikhonov_lambda;
  }
  o.preprocessor.width = s.preprocessor_width;
  o.preprocessor.depth = s.preprocessor_depth;
  o.level_input = s.level_input;
  const int64_t enhancer_inputs = o.level_input ? 8 : 4;  // first stage (+ light level)
  o.enhancer = parse_enhancer(s.enhancer);
  o.unet = s.unet, o.dncnn = s.dncnn, o.rcan = s.rcan, o.nafnet = s.nafnet;
  o.unet.in_channels = o.dncnn.in_channels = o.rcan.in_channels = o.nafnet.in_channels = enhancer_inputs;
  o.unet.bn_momentum = o.bn_momentum;
  require(o.unet.width >= 1 && o.dncnn.width >= 1 && o.rcan.width >= 1 && o.nafnet.width >= 1, "config",
          "model widths must be positive");
  require(o.scene % 16 == 0, "camera", "scene_size must be divisible by 16 for the U-Net");
  check_camera_for_model(o, camera);
  return o;
}

GeneratorOptions generator_options(const Config& config, const CameraConfig& camera, bool initialise) {
  return generator_options(model_spec(config), camera, initialise);
}

const std::vector<OptionField<DiscriminatorOptions>>& discriminator_fields() {
  using O = DiscriminatorOptions;
  static const std::vector<OptionField<O>> fields = {
      {"kind", &O::kind},
      {"width", &O::width, 1, 4096, "1 to 4096 filters"},
  };
  return fields;
}

void register_model_option_tables() {
  static const bool registered = [] {
    register_ranges(range_rows(model_spec_fields(), "model."));
    register_ranges(range_rows(discriminator_fields(), "discriminator."));
    return true;
  }();
  (void)registered;
}

DiscriminatorOptions discriminator_options(const Config& c) {
  DiscriminatorOptions o;
  read_options(c, discriminator_fields(), o, "discriminator.");
  return o;
}

std::string consistency_text(const ModelSpec& spec) {
  if (spec.consistency_strength <= 0) return "";
  std::ostringstream s;
  s << ", pictures corrected by their captures (data consistency c " << spec.consistency_strength << ", blur "
    << spec.consistency_blur << " px)";
  return s.str();
}

double largest_consistency_blur(int64_t scene) { return static_cast<double>(scene - 1) / 3; }

std::string consistency_blur_reach_problem(double sigma, int64_t scene) {
  if (sigma <= largest_consistency_blur(scene)) return "";
  std::ostringstream s;
  s << "a blur of " << sigma << " scene pixels reaches " << std::ceil(3 * sigma) << " pixels (3 sigma), more than "
    << scene << "-pixel scenes hold: at most " << std::setprecision(4) << largest_consistency_blur(scene)
    << " for this camera";
  return s.str();
}

std::string enhancer_text(const ModelSpec& s) {
  std::ostringstream os;
  if (s.enhancer == "unet") os << "U-Net, width " << s.unet.width;
  if (s.enhancer == "dncnn") os << "DnCNN, " << s.dncnn.layers << " layers of " << s.dncnn.width;
  if (s.enhancer == "rcan")
    os << "RCAN, " << s.rcan.groups << " groups x " << s.rcan.blocks << " blocks of " << s.rcan.width;
  if (s.enhancer == "nafnet")
    os << "NAFNet, width " << s.nafnet.width << ", blocks " << s.nafnet.enc_blocks << "/" << s.nafnet.middle_blocks
       << "/" << s.nafnet.dec_blocks;
  return os.str();
}

std::string first_stage_text(const ModelSpec& s) {
  std::string pre;
  if (s.preprocessor_width > 0)
    pre = "measurement pre-processor (" + std::to_string(s.preprocessor_depth) + " convolutions, width " +
          std::to_string(s.preprocessor_width) + "), then ";
  if (s.input == "tikhonov") return pre + "fixed Tikhonov filter (the naive model)";
  return pre + "trainable inversion W1^T Y W2 (" + s.inversion_init + " init, " +
         (s.inversion_shared ? "one pair for all channels" : "one pair per Bayer channel") + ")";
}

}  // namespace flatnet
