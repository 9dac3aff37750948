#include "nn/model_file.hpp"

#include <set>

#include "io/safetensors.hpp"
#include "io/torch_file.hpp"

#include <nlohmann/json.hpp>

#include <chrono>
#include <cmath>
#include <ctime>
#include <fstream>
#include <iomanip>
#include <limits>
#include <regex>

#include "core/error.hpp"
#include "core/precision.hpp"
#include "core/util.hpp"
#include "optics/camera.hpp"
#include "nn/optimizer_state.hpp"
#include "optics/codes.hpp"

namespace flatnet {

namespace {

constexpr const char* kModelFormat = "flatnet-model";
constexpr const char* kCheckpointFormat = "flatnet-checkpoint";
constexpr int kFormatVersion = 2;

// Initial W1 {rows,N,k}, W2 {cols,N,k} for model.inversion.init.
std::pair<torch::Tensor, torch::Tensor> initial_inversion(const Config& c, const CameraConfig& camera) {
  const auto init = c.str("model.inversion.init");
  const bool shared = c.flag("model.inversion.shared");
  const int64_t rows = camera.raw.crop[2], cols = camera.raw.crop[3], n = camera.scene_size;
  const int64_t k = shared ? 1 : 4;
  const auto seed = static_cast<uint64_t>(c.integer("model.inversion.seed"));
  if (init == "transpose") {
    require(!camera.calibration.empty(), "data.camera", "the camera names no calibration (needed for init transpose)");
    const auto calib = load_calibration(camera.calibration, camera);
    if (shared) {
      const int ch = channel_index(c.str("model.inversion.channel"));
      return {calib.P[ch].unsqueeze(2), calib.Q[ch].unsqueeze(2)};
    }
    return {calib.P.permute({1, 2, 0}), calib.Q.permute({1, 2, 0})};
  }
  if (init == "pinv") {
    require(!camera.calibration.empty(), "data.camera", "the camera names no calibration (needed for init pinv)");
    const double lambda = c.num("model.inversion.lambda");
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
    const int ch = channel_index(c.str("model.inversion.channel"));
    for (int64_t i = 0; i < k; ++i) {
      L.push_back(regularised_pinv(calib.P[shared ? ch : i]));
      R.push_back(regularised_pinv(calib.Q[shared ? ch : i]));
    }
    return {torch::stack(L, 2), torch::stack(R, 2)};
  }
  if (init == "calibfree") {
    const double slope = c.num("model.inversion.slope");
    std::vector<torch::Tensor> L, R;
    for (int64_t i = 0; i < k; ++i) {
      L.push_back(calibration_free_phi(rows, n, slope, seed + 2 * i));
      R.push_back(calibration_free_phi(cols, n, slope, seed + 2 * i + 1));
    }
    return {torch::stack(L, 2), torch::stack(R, 2)};
  }
  if (init == "flatnet-toeplitz") {
    const auto left = c.path("model.inversion.toeplitz_file");
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
  throw Error("config: model.inversion.init must be transpose, pinv, calibfree, flatnet-toeplitz, random or transfer, got '" +
              init + "'");
}

// Fills every parameter and buffer of `m` with fetch(name, is_buffer), checking shapes; errors
// about `where` call a tensor "<label> '<its name in the file>'".
void fill_module(
    torch::nn::Module& m, const std::filesystem::path& where, const std::string& label,
    const std::function<torch::Tensor(const std::string&, bool)>& fetch,
    const std::function<std::string(const std::string&)>& name_in_file = [](const std::string& n) { return n; }) {
  torch::NoGradGuard no_grad;
  auto copy_in = [&](const std::string& name, torch::Tensor target, bool buffer) {
    const auto t = fetch(name, buffer);
    if (t.sizes() != target.sizes()) {
      std::ostringstream os;
      os << label << " '" << name_in_file(name) << "' is " << t.sizes() << ", the model needs " << target.sizes();
      throw Error(where, os.str());
    }
    if (t.is_floating_point() && !torch::isfinite(t).all().item<bool>())
      throw Error(where, label + " '" + name_in_file(name) + "' holds NaN or infinity (a damaged file?)");
    target.copy_(t);
  };
  for (auto& p : m.named_parameters()) copy_in(p.key(), p.value(), false);
  for (auto& b : m.named_buffers()) copy_in(b.key(), b.value(), true);
}

// ---- What a model file or checkpoint holds ------------------------------------------------------
//
// Format 2 (this one) is a safetensors file: every tensor under a prefix ("generator.",
// "generator_ema.", "discriminator.", "optimizer_generator.", "optimizer_discriminator."), and the
// strings in __metadata__: format, format_version, config (YAML), camera (YAML), step, best_psnr
// and, for checkpoints, each optimiser's parameter groups (JSON). Python reads it with
// `safetensors.torch.load_file` (no code runs), or with nothing but json and struct.
// Format 1 (before 2026-11) was a TorchScript archive; it is still read, as data
// (read_torchscript_archive), never through LibTorch's loader, which would run its code.

struct Stored {
  std::map<std::string, std::string> meta;
  std::map<std::string, torch::Tensor> tensors;
  int version = kFormatVersion;

  const std::string& text(const std::string& key, const std::filesystem::path& path) const {
    const auto it = meta.find(key);
    if (it == meta.end()) throw Error(path, "not a flatnet file (no '" + key + "' in it)");
    return it->second;
  }
  // Tensors under "<prefix>." with the prefix removed.
  std::map<std::string, torch::Tensor> under(const std::string& prefix) const {
    std::map<std::string, torch::Tensor> out;
    for (const auto& [name, t] : tensors)
      if (name.rfind(prefix + ".", 0) == 0) out[name.substr(prefix.size() + 1)] = t;
    return out;
  }
};

std::string format_number(double v) {
  std::ostringstream os;
  os << std::setprecision(17) << v;
  return os.str();
}

// A format-1 archive's top-level values as format 2 names them.
Stored read_format1(const std::filesystem::path& path) {
  const auto root = read_torchscript_archive(path);
  Stored s;
  s.version = 1;
  for (const auto& [k, v] : root->entries) {
    if (k->kind != PyValue::Kind::string) continue;
    const auto& key = k->text;
    if (v->kind == PyValue::Kind::string) s.meta[key == "flatnet_format" ? "format" : key] = v->text;
    if (v->kind == PyValue::Kind::integer && key == "step") s.meta["step"] = std::to_string(v->integer);
    if (v->kind == PyValue::Kind::real && key == "best_psnr") s.meta["best_psnr"] = format_number(v->real);
    if (v->kind == PyValue::Kind::tensor) s.tensors[key] = v->tensor;
    if (v->is_dict() && (key == "generator" || key == "generator_ema" || key == "discriminator"))
      for (auto& [name, t] : tensors_in(*v)) s.tensors[key + "." + name] = t;
  }
  if (const auto it = s.tensors.find("rng_state"); it != s.tensors.end()) it->second = it->second.to(torch::kUInt8);
  return s;
}

Stored read_stored(const std::filesystem::path& path, const std::string& expected_format) {
  const auto bytes = read_file_text(path, kMaxModelFileBytes);
  Stored s;
  if (looks_like_safetensors(bytes)) {
    auto st = parse_safetensors(bytes, path);
    s.meta = std::move(st.metadata);
    for (auto& [name, t] : st.tensors) s.tensors[name] = t;
    const auto& version = s.text("format_version", path);
    require(version.size() <= 6 && version.find_first_not_of("0123456789") == std::string::npos && !version.empty(),
            path, "format_version '" + version.substr(0, 40) + "' is not a version number");
    s.version = std::stoi(version);
  } else if (bytes.size() >= 4 && bytes.compare(0, 4, "PK\x03\x04") == 0) {
    s = read_format1(path);
  } else {
    throw Error(path, std::string("not a flatnet ") + (expected_format == kModelFormat ? "model" : "checkpoint") +
                          " file (neither safetensors nor a format-1 archive)");
  }
  const auto& format = s.text("format", path);
  if (format != expected_format) {
    if (format == kCheckpointFormat)
      throw Error(path, "this is a training checkpoint; make a model file with `flatnet export --checkpoint " +
                            path.string() + " --out MODEL`");
    throw Error(path, "is a " + format + " file, expected a " + expected_format + " file");
  }
  if (s.version > kFormatVersion)
    throw Error(path, "format version " + std::to_string(s.version) + " is newer than this flatnet reads (" +
                          std::to_string(kFormatVersion) + "); update flatnet");
  return s;
}

// Every parameter and buffer of `m`, prefixed, in the module's order.
void add_module(std::vector<std::pair<std::string, torch::Tensor>>& out, const std::string& prefix,
                torch::nn::Module& m) {
  for (const auto& p : m.named_parameters()) out.emplace_back(prefix + "." + p.key(), p.value());
  for (const auto& b : m.named_buffers()) out.emplace_back(prefix + "." + b.key(), b.value());
}

void load_module(const Stored& s, const std::string& key, torch::nn::Module& m, const std::filesystem::path& where) {
  const auto tensors = s.under(key);
  if (tensors.empty()) throw Error(where, "no '" + key + "' weights in the file");
  fill_module(m, where, key + " weight", [&](const std::string& name, bool) {
    const auto it = tensors.find(name);
    if (it == tensors.end())
      throw Error(where, key + " weights lack '" + name + "' (the file's architecture differs from its config)");
    return it->second;
  });
}

std::string utc_now_iso8601() {
  const auto now = std::chrono::system_clock::to_time_t(std::chrono::system_clock::now());
  std::tm utc{};
  gmtime_r(&now, &utc);
  char text[32];
  std::strftime(text, sizeof text, "%Y-%m-%dT%H:%M:%SZ", &utc);
  return text;
}

std::map<std::string, std::string> header(const std::string& format, const ModelIdentity& identity) {
  std::map<std::string, std::string> meta{{"format", format},
                                          {"format_version", std::to_string(kFormatVersion)},
                                          {"config", identity.config_yaml},
                                          {"camera", camera_geometry_yaml(identity.camera)},
                                          {"written_by", std::string("flatnet ") + FLATNET_VERSION}};
  auto provenance = identity.provenance;
  provenance.written_at = utc_now_iso8601();
  provenance.written_on = cpu_features().summary();
  for (const auto& [key, field] : provenance_fields())
    if (!(provenance.*field).empty()) meta[key] = provenance.*field;
  return meta;
}

Provenance provenance_of(const Stored& s) {
  Provenance p;
  for (const auto& [key, field] : provenance_fields())
    if (const auto it = s.meta.find(key); it != s.meta.end()) p.*field = it->second;
  return p;
}

// The sizes a config claims, checked against the weights the file holds before a network of that
// size is built: a hostile config (width 4096, scene 4194304) would otherwise allocate gigabytes
// first. Each size-setting option is pinned by one tensor's shape; depths (layers, blocks) are
// bounded by the number of tensors present (each layer holds at least one).
void check_sizes_against_weights(const Config& c, const CameraConfig& camera, const Stored& s,
                                 const std::filesystem::path& path) {
  const auto g = s.under("generator");
  auto expect = [&](const std::string& name, int64_t dim, int64_t value, const std::string& option) {
    const auto it = g.find(name);
    require(it != g.end(), path, "has no generator weight '" + name + "' (its config says " + option + ")");
    require(it->second.dim() > dim && it->second.size(dim) == value, path,
            option + " = " + std::to_string(value) + " disagrees with the weights (generator '" + name + "' is " +
                c10::str(it->second.sizes()) + ")");
  };
  const int64_t rows = camera.raw.crop[2], cols = camera.raw.crop[3], n = camera.scene_size;
  if (parse_input_stage(c.str("model.input")) == InputStage::inversion) {
    expect("inversion.PhiL", 0, rows, "camera crop height");
    expect("inversion.PhiL", 1, n, "camera scene_size");
    expect("inversion.PhiR", 0, cols, "camera crop width");
  } else {
    expect("tikhonov.ULt", 1, n, "camera scene_size");
    expect("tikhonov.ULt", 2, rows, "camera crop height");
    expect("tikhonov.UR", 1, cols, "camera crop width");
  }
  const auto enhancer = c.str("model.enhancer");
  const auto count = static_cast<int64_t>(g.size());
  if (enhancer == "unet") expect("enhancer.outc.conv.weight", 1, c.integer("model.unet.width"), "model.unet.width");
  if (enhancer == "dncnn") {
    expect("enhancer.body.0.weight", 0, c.integer("model.dncnn.width"), "model.dncnn.width");
    require(c.integer("model.dncnn.layers") <= count, path, "model.dncnn.layers exceeds the weights the file holds");
  }
  if (enhancer == "rcan") {
    expect("enhancer.head.weight", 0, c.integer("model.rcan.width"), "model.rcan.width");
    require(c.integer("model.rcan.groups") * c.integer("model.rcan.blocks") <= count, path,
            "model.rcan.groups x blocks exceeds the weights the file holds");
  }
  if (enhancer == "nafnet") {
    expect("enhancer.intro.weight", 0, c.integer("model.nafnet.width"), "model.nafnet.width");
    require(4 * (c.integer("model.nafnet.enc_blocks") + c.integer("model.nafnet.dec_blocks")) +
                    c.integer("model.nafnet.middle_blocks") <=
                count,
            path, "model.nafnet block counts exceed the weights the file holds");
  }
  if (const auto d = s.under("discriminator"); !d.empty()) {
    const auto it = d.find("convs.0.weight");
    require(it != d.end() && it->second.dim() == 4 && it->second.size(0) == c.integer("discriminator.width"), path,
            "discriminator.width disagrees with the discriminator's weights");
  }
}

std::pair<Config, CameraConfig> settings(const Stored& s, const std::filesystem::path& path) {
  auto config = Config::from_text(s.text("config", path), path);
  auto camera = camera_from_yaml_text(s.text("camera", path), path);
  check_sizes_against_weights(config, camera, s, path);
  return {config, camera};
}

// The generator (with its config and camera) from a model file or a checkpoint; from a checkpoint
// that kept a moving average of the weights, the average.
ModelFile read_generator(const std::filesystem::path& path, const std::string& format, bool* used_average = nullptr) {
  const auto s = read_stored(path, format);
  auto [config, camera] = settings(s, path);
  ModelFile m{Generator(generator_options(config, camera, false)), config, camera, 2, {}};
  m.format_version = s.version;
  m.provenance = provenance_of(s);
  const bool average = format == kCheckpointFormat && !s.under("generator_ema").empty();
  if (format == kCheckpointFormat) {  // what a model exported from it will say
    const auto text = [&](const char* key) { return s.meta.count(key) ? s.meta.at(key) : std::string(); };
    m.provenance.trained_steps = text("step");
    m.provenance.train_seconds = text("train_seconds");
    const auto best = text("best_psnr");  // -1e9 before the first validation
    const bool scored = is_decimal_number(best) && std::strtod(best.c_str(), nullptr) >= -1e8;
    m.provenance.best_val_psnr = scored ? best : "";
    m.provenance.source = "checkpoint " + path.filename().string() + (average ? " (moving average)" : "");
  }
  if (used_average) *used_average = average;
  load_module(s, average ? "generator_ema" : "generator", *m.generator, path);
  m.generator->eval();
  return m;
}

// ---- Optimiser state as tensors and JSON ---------------------------------------------------------
// Adam's moments per parameter, named by the parameter ("optimizer_generator.<name>.exp_avg",
// ".exp_avg_sq", ".max_exp_avg_sq", ".step"), and its groups' options with their parameters' names
// in the metadata. LibTorch keys its state by tensor address, which means nothing in a file.

std::string state_key(const torch::Tensor& p) { return c10::guts::to_string(p.unsafeGetTensorImpl()); }

std::map<const void*, std::string> parameter_names(torch::nn::Module& m) {
  std::map<const void*, std::string> names;
  for (const auto& p : m.named_parameters()) names[p.value().unsafeGetTensorImpl()] = p.key();
  return names;
}

std::string save_optimizer(std::vector<std::pair<std::string, torch::Tensor>>& out, const std::string& prefix,
                           torch::optim::Adam& opt, torch::nn::Module& m) {
  const auto names = parameter_names(m);
  nlohmann::json groups = nlohmann::json::array();
  for (auto& group : opt.param_groups()) {
    const auto& o = static_cast<const torch::optim::AdamOptions&>(group.options());
    nlohmann::json g = {{"lr", o.lr()},
                        {"betas", {std::get<0>(o.betas()), std::get<1>(o.betas())}},
                        {"eps", o.eps()},
                        {"weight_decay", o.weight_decay()},
                        {"amsgrad", o.amsgrad()},
                        {"params", nlohmann::json::array()}};
    for (const auto& p : group.params()) {
      const auto name = names.at(p.unsafeGetTensorImpl());
      g["params"].push_back(name);
      const auto it = opt.state().find(state_key(p));
      if (it == opt.state().end()) continue;  // no step taken yet
      const auto& st = static_cast<const torch::optim::AdamParamState&>(*it->second);
      const auto base = prefix + "." + name + ".";
      out.emplace_back(base + "step", torch::tensor(st.step(), torch::kInt64));
      out.emplace_back(base + "exp_avg", st.exp_avg());
      out.emplace_back(base + "exp_avg_sq", st.exp_avg_sq());
      if (st.max_exp_avg_sq().defined()) out.emplace_back(base + "max_exp_avg_sq", st.max_exp_avg_sq());
    }
    groups.push_back(g);
  }
  return groups.dump();
}

nlohmann::json parse_groups(const std::string& text, const std::filesystem::path& path, const std::string& key) {
  try {
    auto j = nlohmann::json::parse(text, [&](int depth, nlohmann::json::parse_event_t, nlohmann::json&) {
      if (depth > 4) throw Error(path, key + " nests too deeply");
      return true;
    });
    require(j.is_array(), path, key + " is not a list of parameter groups");
    return j;
  } catch (const nlohmann::json::exception& e) {
    throw Error(path, key + " is not valid JSON (" + std::string(e.what()).substr(0, 120) + ")");
  }
}

void load_optimizer(const Stored& s, const std::string& prefix, torch::optim::Adam& opt, torch::nn::Module& m,
                    const std::filesystem::path& path) {
  const auto groups = parse_groups(s.text(prefix, path), path, prefix);
  auto& ours = opt.param_groups();
  require(groups.size() == ours.size(), path,
          prefix + " has " + std::to_string(groups.size()) + " parameter groups, the trainer " +
              std::to_string(ours.size()));
  const auto names = parameter_names(m);
  const auto tensors = s.under(prefix);
  for (size_t i = 0; i < ours.size(); ++i) {
    const auto& g = groups[i];
    auto& o = static_cast<torch::optim::AdamOptions&>(ours[i].options());
    try {
      o.lr(g.at("lr").get<double>());
      o.betas({g.at("betas").at(0).get<double>(), g.at("betas").at(1).get<double>()});
      o.eps(g.at("eps").get<double>());
      o.weight_decay(g.at("weight_decay").get<double>());
      o.amsgrad(g.at("amsgrad").get<bool>());
    } catch (const nlohmann::json::exception&) {
      throw Error(path, prefix + " group " + std::to_string(i) + " lacks lr, betas, eps, weight_decay or amsgrad");
    }
    require_adam_options(std::get<0>(o.betas()), std::get<1>(o.betas()), o.eps(), o.lr(), o.weight_decay(), path,
                         prefix + " group " + std::to_string(i));
    const auto& params = ours[i].params();
    require(g.contains("params") && g["params"].is_array() && g["params"].size() == params.size(), path,
            prefix + " group " + std::to_string(i) + " lists other parameters than the trainer's");
    for (size_t j = 0; j < params.size(); ++j) {
      const auto& p = params[j];
      const auto name = names.at(p.unsafeGetTensorImpl());
      require(g["params"][j].is_string() && g["params"][j].get<std::string>() == name, path,
              prefix + " group " + std::to_string(i) + " parameter " + std::to_string(j) + " is not '" + name + "'");
      const auto moment = [&](const std::string& what, bool required) -> torch::Tensor {
        const auto it = tensors.find(name + "." + what);
        if (it == tensors.end()) {
          require(!required, path, prefix + " lacks '" + name + "." + what + "'");
          return {};
        }
        if (what == "step") {
          require(it->second.numel() == 1 && it->second.scalar_type() == torch::kInt64, path,
                  prefix + " '" + name + ".step' is not one integer");
          return it->second;
        }
        require(it->second.sizes() == p.sizes(), path,
                prefix + " '" + name + "." + what + "' is " + c10::str(it->second.sizes()) + ", the parameter " +
                    c10::str(p.sizes()));
        require(torch::isfinite(it->second).all().item<bool>(), path,
                prefix + " '" + name + "." + what + "' holds NaN or infinity");
        return it->second.to(torch::kFloat32).clone();
      };
      const auto step = moment("step", false);
      if (!step.defined()) {
        opt.state().erase(state_key(p));
        continue;
      }
      auto st = std::make_unique<torch::optim::AdamParamState>();
      st->step(step.item<int64_t>());
      st->exp_avg(moment("exp_avg", true));
      st->exp_avg_sq(moment("exp_avg_sq", true));
      require_adam_moments(st->step(), st->exp_avg(), st->exp_avg_sq(), path, prefix + " '" + name + ".");
      if (auto mx = moment("max_exp_avg_sq", false); mx.defined()) {
        require(mx.min().item<double>() >= 0, path, prefix + " '" + name + ".max_exp_avg_sq' holds negative values");
        st->max_exp_avg_sq(mx);
      }
      opt.state()[state_key(p)] = std::move(st);
    }
  }
}

double stored_number(const Stored& s, const std::string& key, const std::filesystem::path& path) {
  const auto& text = s.text(key, path);
  require(is_decimal_number(text) || text == "-inf", path, key + " '" + text + "' is not a number");
  return text == "-inf" ? -std::numeric_limits<double>::infinity() : std::strtod(text.c_str(), nullptr);
}

}  // namespace

GeneratorOptions generator_options(const Config& c, const CameraConfig& camera, bool initialise) {
  GeneratorOptions o;
  o.rows = camera.raw.crop[2];
  o.cols = camera.raw.crop[3];
  o.scene = camera.scene_size;
  o.input = parse_input_stage(c.str("model.input"));
  o.bn_momentum = c.num("model.bn_momentum");
  if (o.input == InputStage::inversion) {
    const int64_t k = c.flag("model.inversion.shared") ? 1 : 4;
    if (initialise) {
      std::tie(o.inversion.phil, o.inversion.phir) = initial_inversion(c, camera);
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
  o.level_input = c.flag("model.level_input");
  const int64_t enhancer_inputs = o.level_input ? 8 : 4;  // first stage (+ light level)
  o.unet.in_channels = o.dncnn.in_channels = o.rcan.in_channels = o.nafnet.in_channels = enhancer_inputs;
  o.enhancer = parse_enhancer(c.str("model.enhancer"));
  read_options(c, unet_fields(), o.unet, "model.unet.");
  read_options(c, dncnn_fields(), o.dncnn, "model.dncnn.");
  read_options(c, rcan_fields(), o.rcan, "model.rcan.");
  read_options(c, nafnet_fields(), o.nafnet, "model.nafnet.");
  o.unet.bn_momentum = o.bn_momentum;
  require(o.unet.width >= 1 && o.dncnn.width >= 1 && o.rcan.width >= 1 && o.nafnet.width >= 1, "config",
          "model widths must be positive");
  require(o.scene % 16 == 0, "camera", "scene_size must be divisible by 16 for the U-Net");
  check_camera_for_model(o, camera);
  return o;
}

const std::vector<OptionField<UNetOptions>>& unet_fields() {
  static const std::vector<OptionField<UNetOptions>> fields = {{"width", &UNetOptions::width}};
  return fields;
}

const std::vector<OptionField<DnCNNOptions>>& dncnn_fields() {
  static const std::vector<OptionField<DnCNNOptions>> fields = {{"layers", &DnCNNOptions::layers},
                                                                {"width", &DnCNNOptions::width}};
  return fields;
}

const std::vector<OptionField<RCANOptions>>& rcan_fields() {
  using O = RCANOptions;
  static const std::vector<OptionField<O>> fields = {
      {"groups", &O::groups}, {"blocks", &O::blocks}, {"width", &O::width}, {"reduction", &O::reduction}};
  return fields;
}

const std::vector<OptionField<NAFNetOptions>>& nafnet_fields() {
  using O = NAFNetOptions;
  static const std::vector<OptionField<O>> fields = {{"width", &O::width},
                                                     {"enc_blocks", &O::enc_blocks},
                                                     {"middle_blocks", &O::middle_blocks},
                                                     {"dec_blocks", &O::dec_blocks}};
  return fields;
}

DiscriminatorOptions discriminator_options(const Config& c) {
  DiscriminatorOptions o;
  o.kind = c.str("discriminator.kind");
  o.width = c.integer("discriminator.width");
  return o;
}

ModelIdentity model_identity(const Config& config, const CameraConfig& camera) { return {config.to_yaml(), camera, {}}; }

std::vector<std::pair<std::string, std::string Provenance::*>> provenance_fields() {
  return {{"trained_steps", &Provenance::trained_steps}, {"train_seconds", &Provenance::train_seconds},
          {"best_val_psnr", &Provenance::best_val_psnr}, {"written_at", &Provenance::written_at},
          {"written_on", &Provenance::written_on},       {"source", &Provenance::source},
          {"scores", &Provenance::scores}};
}

void save_model_file(const std::filesystem::path& path, Generator& generator, const Config& config,
                     const CameraConfig& camera, const Provenance& provenance) {
  auto identity = model_identity(config, camera);
  identity.provenance = provenance;
  save_model_file(path, generator, identity);
}

void save_model_file(const std::filesystem::path& path, Generator& generator, const ModelIdentity& identity) {
  std::vector<std::pair<std::string, torch::Tensor>> tensors;
  add_module(tensors, "generator", *generator);
  write_safetensors(path, tensors, header(kModelFormat, identity));
}

ModelFile load_model_file(const std::filesystem::path& path) { return read_generator(path, kModelFormat); }

void save_checkpoint(const std::filesystem::path& path, Generator& g, Discriminator& d, torch::optim::Adam& opt_g,
                     torch::optim::Adam& opt_d, const TrainState& state, const ModelIdentity& identity,
                     Generator* ema, const CheckpointCamera& camera) {
  std::vector<std::pair<std::string, torch::Tensor>> tensors;
  add_module(tensors, "generator", *g);
  if (ema) add_module(tensors, "generator_ema", **ema);
  add_module(tensors, "discriminator", *d);
  auto meta = header(kCheckpointFormat, identity);
  meta["optimizer_generator"] = save_optimizer(tensors, "optimizer_generator", opt_g, *g);
  meta["optimizer_discriminator"] = save_optimizer(tensors, "optimizer_discriminator", opt_d, *d);
  if (camera.module) {
    add_module(tensors, "camera", *camera.module);
    meta["optimizer_camera"] = save_optimizer(tensors, "optimizer_camera", *camera.optimizer, *camera.module);
  }
  meta["step"] = std::to_string(state.step);
  meta["best_psnr"] = format_number(state.best_psnr);
  meta["train_seconds"] = format_number(state.train_seconds);
  if (!state.run_id.empty()) meta["run_id"] = state.run_id;
  tensors.emplace_back("rng_state", state.rng_state);
  write_safetensors(path, tensors, meta);
}

CheckpointSettings checkpoint_settings(const std::filesystem::path& path) {
  const auto s = read_stored(path, kCheckpointFormat);
  CheckpointSettings out;
  std::tie(out.config, out.camera) = settings(s, path);
  if (const auto it = s.meta.find("run_id"); it != s.meta.end()) {
    require(it->second.size() == 16 && it->second.find_first_not_of("0123456789abcdef") == std::string::npos, path,
            "run_id is not 16 hex digits");
    out.run_id = it->second;
  }
  return out;
}

TrainState load_checkpoint(const std::filesystem::path& path, Generator& g, Discriminator& d, torch::optim::Adam& opt_g,
                           torch::optim::Adam& opt_d, Generator* ema, const CheckpointCamera& camera) {
  const auto s = read_stored(path, kCheckpointFormat);
  settings(s, path);
  const bool has_camera = !s.under("camera").empty();
  require(has_camera == (camera.module != nullptr), path,
          has_camera ? "holds a learned camera (a co-design run), and this run learns none"
                     : "holds no learned camera, and this run learns one (codes.learn)");
  load_module(s, "generator", *g, path);
  if (ema) load_module(s, s.under("generator_ema").empty() ? "generator" : "generator_ema", **ema, path);
  load_module(s, "discriminator", *d, path);
  if (camera.module) load_module(s, "camera", *camera.module, path);
  TrainState st;
  if (const auto id = s.meta.find("run_id"); id != s.meta.end()) st.run_id = id->second;
  st.optimizers_restored = s.version >= 2;
  if (st.optimizers_restored) {  // format 1 kept LibTorch's own optimiser archives; their moments start afresh
    load_optimizer(s, "optimizer_generator", opt_g, *g, path);
    load_optimizer(s, "optimizer_discriminator", opt_d, *d, path);
    if (camera.module) load_optimizer(s, "optimizer_camera", *camera.optimizer, *camera.module, path);
  }
  const auto step = stored_number(s, "step", path);
  require(step >= 0 && step < 1e15 && step == std::floor(step), path, "step is not a count");
  st.step = static_cast<int64_t>(step);
  st.best_psnr = stored_number(s, "best_psnr", path);
  if (s.meta.count("train_seconds")) {
    st.train_seconds = stored_number(s, "train_seconds", path);
    require(std::isfinite(st.train_seconds) && st.train_seconds >= 0, path, "train_seconds is not a duration");
  }
  const auto rng = s.tensors.find("rng_state");
  require(rng != s.tensors.end(), path, "has no rng_state");
  require_cpu_generator_state(rng->second, path, "rng_state");
  st.rng_state = rng->second;
  return st;
}

double checkpoint_best_psnr(const std::filesystem::path& path) {
  return stored_number(read_stored(path, kCheckpointFormat), "best_psnr", path);
}

bool is_checkpoint_file(const std::filesystem::path& path) {
  const auto bytes = read_file_text(path, kMaxModelFileBytes);
  if (looks_like_safetensors(bytes)) {
    const auto st = parse_safetensors(bytes, path);
    const auto it = st.metadata.find("format");
    return it != st.metadata.end() && it->second == kCheckpointFormat;
  }
  if (bytes.compare(0, 4, "PK\x03\x04") == 0) {
    const auto meta = read_format1(path).meta;
    const auto it = meta.find("format");
    return it != meta.end() && it->second == kCheckpointFormat;
  }
  return false;
}

int model_file_version(const std::filesystem::path& path) {
  const auto bytes = read_file_text(path, kMaxModelFileBytes);
  if (looks_like_safetensors(bytes)) return kFormatVersion;
  return bytes.compare(0, 4, "PK\x03\x04") == 0 ? 1 : 0;
}

ModelFile model_from_checkpoint(const std::filesystem::path& path, bool* used_average) {
  return read_generator(path, kCheckpointFormat, used_average);
}

void init_generator_from(const std::filesystem::path& model, Generator& g, GeneratorPart part) {
  auto m = load_model_file(model);
  const auto theirs = m.generator->named_parameters(), their_buffers = m.generator->named_buffers();
  const bool adds_level = g->options().level_input && !m.generator->options().level_input;
  const auto ours = g->named_parameters(), our_buffers = g->named_buffers();
  auto first_stage = [](const std::string& name) {
    return name.rfind("inversion.", 0) == 0 || name.rfind("tikhonov.", 0) == 0;
  };
  if (part == GeneratorPart::enhancer)
    require(m.generator->options().input == g->options().input, model,
            "its first stage (model.input) differs from this config's; experiment.reinit inversion keeps the stage's kind");
  fill_module(*g, model, "weight", [&](const std::string& name, bool buffer) {
    if (part == GeneratorPart::enhancer && first_stage(name)) {
      const auto* own = buffer ? our_buffers.find(name) : ours.find(name);
      return own->detach().clone();  // this camera's, as initialised
    }
    const auto* t = buffer ? their_buffers.find(name) : theirs.find(name);
    if (!t)
      throw Error(model,
                  "has no '" + name + "': its architecture (model.input, model.enhancer) differs from this config's");
    const auto* mine = buffer ? nullptr : ours.find(name);
    if (adds_level && mine && t->dim() == 4 && mine->dim() == 4 && t->size(1) == 4 && mine->size(1) == 8) {
      // The enhancer's first convolution gains the four level channels with zero weights: the
      // model starts out computing exactly what the file's model computes.
      auto padded = torch::zeros(mine->sizes(), t->options());
      padded.narrow(1, 0, 4).copy_(*t);
      return padded;
    }
    return t->detach();
  });
}

void transfer_inversion(const std::filesystem::path& source, const CalibrationPair& c, double lambda, Generator& g) {
  require(lambda > 0 && std::isfinite(lambda), "model.inversion.lambda", "must be positive");
  const auto m = load_model_file(source);
  const auto old_params = m.generator->named_parameters();
  const auto* old_l = old_params.find("inversion.PhiL");
  const auto* old_r = old_params.find("inversion.PhiR");
  require(old_l && old_r, source, "has no trainable inversion to transfer (model.input is not inversion)");
  auto params = g->named_parameters();
  auto* new_l = params.find("inversion.PhiL");
  auto* new_r = params.find("inversion.PhiR");
  require(new_l && new_r, "model.input", "transfer needs an inversion first stage");
  require(old_l->size(1) == new_l->size(1), source, "its scene size differs from this camera's");
  int shared_channel = 1;
  // One side: W_old {m_old,N,k}, P_old/P_new {4,m,N} -> W_new {m_new,N,k}.
  auto side = [&](const torch::Tensor& w_old, const torch::Tensor& p_old, const torch::Tensor& p_new, int64_t k) {
    std::vector<torch::Tensor> out;
    for (int64_t i = 0; i < k; ++i) {
      const int64_t ch = k == 1 ? shared_channel : i;  // a shared inversion is one channel's (model.inversion.channel)
      const auto M = torch::matmul(w_old.select(2, i).to(torch::kFloat64).t(), p_old[ch]);  // {N,N}
      auto [U, S, Vh] = torch::linalg::svd(p_new[ch], false, c10::nullopt);
      const auto smax = S.max();
      const auto filter = S / (S * S + lambda * smax * smax);
      out.push_back(torch::matmul(U * filter.unsqueeze(0), torch::matmul(Vh, M.t())));  // {m_new,N}
    }
    return torch::stack(out, 2).to(torch::kFloat32);
  };
  const int64_t k = new_l->size(2);
  require(old_l->size(2) == k, source, "its inversion is " + std::string(k == 1 ? "per channel" : "shared") +
                                           ", this config's is not (model.inversion.shared)");
  shared_channel = channel_index(m.config.str("model.inversion.channel"));
  torch::NoGradGuard no_grad;
  new_l->copy_(side(*old_l, c.P_old, c.P_new, k));
  new_r->copy_(side(*old_r, c.Q_old, c.Q_new, k));
}

std::string flatnet_name(const std::string& ours) {
  for (const std::string prefix : {"inversion.", "enhancer."})
    if (ours.rfind(prefix, 0) == 0) return ours.substr(prefix.size());
  return ours;
}

void export_state_dict(const std::filesystem::path& path, Generator& generator, StateDictLayout layout) {
  // PyTorch's state_dict order: each module's parameters, then its buffers, depth first.
  std::vector<std::pair<std::string, torch::Tensor>> tensors;
  std::function<void(torch::nn::Module&, const std::string&)> visit = [&](torch::nn::Module& m,
                                                                          const std::string& prefix) {
    for (const auto& p : m.named_parameters(/*recurse=*/false))
      tensors.emplace_back(flatnet_name(prefix + p.key()), p.value());
    for (const auto& b : m.named_buffers(/*recurse=*/false))
      tensors.emplace_back(flatnet_name(prefix + b.key()), b.value());
    for (const auto& c : m.named_children()) visit(*c.value(), prefix + c.key() + ".");
  };
  visit(*generator, "");
  save_torch_state_dict(path, tensors, layout == StateDictLayout::flatnet_checkpoint ? "gen_state_dict" : "");
}

namespace {

bool holds_tensors(const PyValue& v) {
  for (const auto& e : v.entries)
    if (e.second->kind == PyValue::Kind::tensor) return true;
  return false;
}

// The generator's state dict within what torch.save wrote: FlatNet's checkpoint
// ({'gen_state_dict': ..., 'optimizerG_state_dict': ...}), a plain or ordered state dict, or one
// dict of tensors under a single well-known key.
const PyValue& find_generator_dict(const PyValue& root, const std::filesystem::path& path, std::string& where) {
  require(root.is_dict(), path, "holds a " + root.describe() + ", not a dict of tensors");
  for (const char* key : {"gen_state_dict", "generator", "state_dict", "model"})
    if (auto v = root.get(key); v && v->is_dict() && holds_tensors(*v)) {
      where = std::string("'") + key + "'";
      return *v;
    }
  if (holds_tensors(root)) {
    where = "the top-level dict";
    return root;
  }
  std::string keys;
  for (const auto& e : root.entries)
    keys += (keys.empty() ? "" : ", ") + (e.first->kind == PyValue::Kind::string ? e.first->text : e.first->describe());
  throw Error(path, "holds no state dict: no tensors at the top level and no gen_state_dict (keys: " + keys + ")");
}

}  // namespace

ImportReport import_state_dict(const std::filesystem::path& path, Generator& generator) {
  const auto root = read_torch_file(path);
  ImportReport rep;
  const auto& dict = find_generator_dict(*root, path, rep.source);
  std::map<std::string, torch::Tensor> tensors;
  const auto named = tensors_in(dict);
  // DataParallel saves every name with a "module." prefix.
  const bool parallel = !named.empty() && std::all_of(named.begin(), named.end(),
                                                      [](const auto& kv) { return kv.first.rfind("module.", 0) == 0; });
  for (const auto& [name, t] : named) tensors[parallel ? name.substr(7) : name] = t;
  rep.data_parallel = parallel;
  std::set<std::string> used;
  fill_module(
      *generator, path, "tensor",
      [&](const std::string& ours, bool) {
        const auto name = flatnet_name(ours);
        const auto it = tensors.find(name);
        require(it != tensors.end(), path, "has no tensor '" + name + "' (in " + rep.source + ") that the model needs");
        used.insert(name);
        return it->second;
      },
      flatnet_name);
  for (const auto& [name, t] : tensors)
    if (!used.count(name)) rep.unused.push_back(name);
  rep.used = static_cast<int64_t>(used.size());
  return rep;
}

}  // namespace flatnet
