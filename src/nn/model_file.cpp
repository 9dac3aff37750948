#include "nn/model_file.hpp"

#include <set>

#include "io/torch_file.hpp"

#include <fstream>
#include <regex>

#include "core/error.hpp"
#include "core/util.hpp"
#include "optics/camera.hpp"
#include "optics/codes.hpp"

namespace flatnet {

namespace {

constexpr const char* kModelFormat = "flatnet-model";
constexpr const char* kCheckpointFormat = "flatnet-checkpoint";
constexpr int64_t kFormatVersion = 1;

int channel_index(const std::string& name) {
  for (int c = 0; c < 4; ++c)
    if (name == kChannelNames[c]) return c;
  throw Error("config: model.inversion.channel must be b, gb, gr or r, got '" + name + "'");
}

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
  if (init == "random") {
    auto gen = at::detail::createCPUGenerator(seed);
    const double scale = 1.0 / std::sqrt(static_cast<double>(rows));
    return {at::randn({rows, n, k}, gen) * scale, at::randn({cols, n, k}, gen) * scale};
  }
  throw Error("config: model.inversion.init must be transpose, pinv, calibfree, flatnet-toeplitz or random, got '" +
              init + "'");
}

void write_string(torch::serialize::OutputArchive& a, const std::string& key, const std::string& value) {
  a.write(key, c10::IValue(value));
}

std::string read_string(torch::serialize::InputArchive& a, const std::string& key, const std::filesystem::path& where) {
  c10::IValue v;
  if (!a.try_read(key, v) || !v.isString()) throw Error(where, "not a flatnet file (no '" + key + "')");
  return v.toStringRef();
}

void save_module(torch::serialize::OutputArchive& root, const std::string& key, torch::nn::Module& m) {
  torch::serialize::OutputArchive a(root.compilation_unit());
  m.save(a);
  root.write(key, a);
}

// Reads tensor `dotted` ("enhancer.inc.conv.conv.0.weight") from the nested archives Module::save writes.
bool read_nested(torch::serialize::InputArchive& a, const std::string& dotted, torch::Tensor& t, bool buffer) {
  const auto dot = dotted.find('.');
  if (dot == std::string::npos) return a.try_read(dotted, t, buffer);
  torch::serialize::InputArchive sub;
  if (!a.try_read(dotted.substr(0, dot), sub)) return false;
  return read_nested(sub, dotted.substr(dot + 1), t, buffer);
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

void load_module(torch::serialize::InputArchive& root, const std::string& key, torch::nn::Module& m,
                 const std::filesystem::path& where) {
  torch::serialize::InputArchive a;
  if (!root.try_read(key, a)) throw Error(where, "no '" + key + "' weights in the file");
  fill_module(m, where, key + " weight", [&](const std::string& name, bool buffer) {
    torch::Tensor t;
    if (!read_nested(a, name, t, buffer))
      throw Error(where, key + " weights lack '" + name + "' (the file's architecture differs from its config)");
    return t;
  });
}

torch::serialize::InputArchive open_archive(const std::filesystem::path& path, const std::string& expected_format) {
  require(std::filesystem::exists(path), path, "no such file");
  verify_zip_crcs(path);  // LibTorch's reader would load a damaged block as wrong weights
  torch::serialize::InputArchive a;
  try {
    a.load_from(path.string());
  } catch (const c10::Error&) {
    throw Error(path, "not a flatnet " + std::string(expected_format == kModelFormat ? "model" : "checkpoint") +
                          " file (not a torch archive)");
  }
  const auto format = read_string(a, "flatnet_format", path);
  if (format != expected_format) {
    if (format == kCheckpointFormat)
      throw Error(path, "this is a training checkpoint; make a model file with `flatnet export --checkpoint " +
                            path.string() + " --out MODEL`");
    throw Error(path, "is a " + format + " file, expected a " + expected_format + " file");
  }
  c10::IValue version;
  a.read("flatnet_version", version);
  if (version.toInt() > kFormatVersion)
    throw Error(path, "format version " + std::to_string(version.toInt()) + " is newer than this flatnet reads (" +
                          std::to_string(kFormatVersion) + "); update flatnet");
  return a;
}

// The archive in memory: LibTorch's file writer aborts the process when the disk fills up (it
// throws from a destructor); written from memory, a full disk is an ordinary, checked error.
std::string archive_bytes(torch::serialize::OutputArchive& a) {
  std::string bytes;
  a.save_to([&](const void* data, size_t n) {
    bytes.append(static_cast<const char*>(data), n);
    return n;
  });
  return bytes;
}

void write_header(torch::serialize::OutputArchive& a, const std::string& format, const ModelIdentity& identity) {
  write_string(a, "flatnet_format", format);
  a.write("flatnet_version", c10::IValue(kFormatVersion));
  write_string(a, "config", identity.config_yaml);
  write_string(a, "camera", camera_geometry_yaml(identity.camera));
}

std::pair<Config, CameraConfig> read_header(torch::serialize::InputArchive& a, const std::filesystem::path& path) {
  auto config = Config::from_text(read_string(a, "config", path), path);
  auto camera = camera_from_yaml_text(read_string(a, "camera", path), path);
  return {config, camera};
}

// The generator (with its config and camera) from a model file or a checkpoint; from a checkpoint
// that kept a moving average of the weights, the average.
ModelFile read_generator(const std::filesystem::path& path, const std::string& format, bool* used_average = nullptr) {
  auto a = open_archive(path, format);
  auto [config, camera] = read_header(a, path);
  ModelFile m{Generator(generator_options(config, camera, false)), config, camera};
  torch::serialize::InputArchive probe;
  const bool average = format == kCheckpointFormat && a.try_read("generator_ema", probe);
  if (used_average) *used_average = average;
  load_module(a, average ? "generator_ema" : "generator", *m.generator, path);
  m.generator->eval();
  return m;
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
  o.unet.in_channels = o.dncnn.in_channels = o.rcan.in_channels = enhancer_inputs;
  o.enhancer = parse_enhancer(c.str("model.enhancer"));
  o.unet.width = c.integer("model.unet.width");
  o.unet.bn_momentum = o.bn_momentum;
  o.dncnn.layers = c.integer("model.dncnn.layers");
  o.dncnn.width = c.integer("model.dncnn.width");
  o.rcan.groups = c.integer("model.rcan.groups");
  o.rcan.blocks = c.integer("model.rcan.blocks");
  o.rcan.width = c.integer("model.rcan.width");
  o.rcan.reduction = c.integer("model.rcan.reduction");
  require(o.unet.width >= 1 && o.dncnn.width >= 1 && o.rcan.width >= 1, "config", "model widths must be positive");
  require(o.scene % 16 == 0, "camera", "scene_size must be divisible by 16 for the U-Net");
  check_camera_for_model(o, camera);
  return o;
}

DiscriminatorOptions discriminator_options(const Config& c) {
  DiscriminatorOptions o;
  o.kind = c.str("discriminator.kind");
  o.width = c.integer("discriminator.width");
  return o;
}

ModelIdentity model_identity(const Config& config, const CameraConfig& camera) { return {config.to_yaml(), camera}; }

void save_model_file(const std::filesystem::path& path, Generator& generator, const Config& config,
                     const CameraConfig& camera) {
  save_model_file(path, generator, model_identity(config, camera));
}

void save_model_file(const std::filesystem::path& path, Generator& generator, const ModelIdentity& identity) {
  torch::serialize::OutputArchive a;
  write_header(a, kModelFormat, identity);
  save_module(a, "generator", *generator);
  write_bytes_atomically(path, archive_bytes(a));
}

ModelFile load_model_file(const std::filesystem::path& path) { return read_generator(path, kModelFormat); }

void save_checkpoint(const std::filesystem::path& path, Generator& g, Discriminator& d, torch::optim::Adam& opt_g,
                     torch::optim::Adam& opt_d, const TrainState& state, const ModelIdentity& identity,
                     Generator* ema) {
  torch::serialize::OutputArchive a;
  write_header(a, kCheckpointFormat, identity);
  save_module(a, "generator", *g);
  if (ema) save_module(a, "generator_ema", **ema);
  save_module(a, "discriminator", *d);
  torch::serialize::OutputArchive og(a.compilation_unit()), od(a.compilation_unit());
  opt_g.save(og);
  opt_d.save(od);
  a.write("optimizer_generator", og);
  a.write("optimizer_discriminator", od);
  a.write("step", c10::IValue(state.step));
  a.write("best_psnr", c10::IValue(state.best_psnr));
  a.write("rng_state", state.rng_state, /*is_buffer=*/true);
  write_bytes_atomically(path, archive_bytes(a));
}

std::pair<Config, CameraConfig> checkpoint_settings(const std::filesystem::path& path) {
  auto a = open_archive(path, kCheckpointFormat);
  return read_header(a, path);
}

TrainState load_checkpoint(const std::filesystem::path& path, Generator& g, Discriminator& d, torch::optim::Adam& opt_g,
                           torch::optim::Adam& opt_d, Generator* ema) {
  auto a = open_archive(path, kCheckpointFormat);
  load_module(a, "generator", *g, path);
  if (ema) {
    torch::serialize::InputArchive probe;
    load_module(a, a.try_read("generator_ema", probe) ? "generator_ema" : "generator", **ema, path);
  }
  load_module(a, "discriminator", *d, path);
  torch::serialize::InputArchive og, od;
  a.read("optimizer_generator", og);
  a.read("optimizer_discriminator", od);
  opt_g.load(og);
  opt_d.load(od);
  TrainState s;
  c10::IValue v;
  a.read("step", v);
  s.step = v.toInt();
  a.read("best_psnr", v);
  s.best_psnr = v.toDouble();
  a.read("rng_state", s.rng_state, true);
  return s;
}

ModelFile model_from_checkpoint(const std::filesystem::path& path, bool* used_average) {
  return read_generator(path, kCheckpointFormat, used_average);
}

void init_generator_from(const std::filesystem::path& model, Generator& g) {
  auto m = load_model_file(model);
  const auto theirs = m.generator->named_parameters(), their_buffers = m.generator->named_buffers();
  const bool adds_level = g->options().level_input && !m.generator->options().level_input;
  const auto ours = g->named_parameters();
  fill_module(*g, model, "weight", [&](const std::string& name, bool buffer) {
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
