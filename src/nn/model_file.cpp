#include "nn/model_file.hpp"

#include <cmath>
#include <set>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/safetensors.hpp"
#include "io/torch_file.hpp"
#include "nn/model_record.hpp"
#include "nn/stored_file.hpp"
#include "optics/camera.hpp"

namespace flatnet {

using detail::kCheckpointFormat;
using detail::kFormatVersion;
using detail::kModelFormat;

void save_model_file(const std::filesystem::path& path, Generator& generator, const Config& config,
                     const CameraConfig& camera, const Provenance& provenance) {
  auto identity = model_identity(config, camera);
  identity.provenance = provenance;
  save_model_file(path, generator, identity);
}

void save_model_file(const std::filesystem::path& path, Generator& generator, const ModelIdentity& identity) {
  std::vector<std::pair<std::string, torch::Tensor>> tensors;
  detail::add_module(tensors, "generator", *generator);
  write_safetensors(path, tensors, detail::header(kModelFormat, identity));
}

ModelFile load_model_file(const std::filesystem::path& path) {
  return detail::read_generator(detail::read_stored(path, kModelFormat), path);
}

bool is_checkpoint_file(const std::filesystem::path& path) {
  // The header alone (a checkpoint is ~48 MB at width 32): 8 length bytes, then the JSON object.
  const auto head = read_file_head(path, 9);
  if (head.size() == 9 && head[8] == '{') {
    const auto metadata = read_safetensors_metadata(path);
    const auto it = metadata.find("format");
    return it != metadata.end() && it->second == kCheckpointFormat;
  }
  if (head.compare(0, 4, "PK\x03\x04") == 0) {
    const auto meta = detail::read_format1(path).meta;
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

void init_generator_from(const std::filesystem::path& model, Generator& g, GeneratorPart part) {
  init_generator_from(load_model_file(model), model, g, part);
}

void init_generator_from(const ModelFile& m, const std::filesystem::path& model, Generator& g, GeneratorPart part) {
  const auto theirs = m.generator->named_parameters(), their_buffers = m.generator->named_buffers();
  const bool adds_level = g->options().level_input && !m.generator->options().level_input;
  const auto ours = g->named_parameters(), our_buffers = g->named_buffers();
  auto first_stage = [](const std::string& name) {
    return name.rfind("inversion.", 0) == 0 || name.rfind("tikhonov.", 0) == 0;
  };
  if (part == GeneratorPart::enhancer)
    require(m.generator->options().input == g->options().input, model,
            "its first stage (model.input) differs from this config's; " + option_key("experiment.reinit") +
                " inversion keeps the stage's kind");
  std::set<std::string> taken;  // the file's tensors this config's model takes
  detail::fill_module(*g, model, "weight", [&](const std::string& name, bool buffer) {
    taken.insert(name);
    if (part == GeneratorPart::enhancer && first_stage(name)) {
      const auto* own = buffer ? our_buffers.find(name) : ours.find(name);
      return own->detach().clone();  // this camera's, as initialised
    }
    const auto* t = buffer ? their_buffers.find(name) : theirs.find(name);
    if (!t && name.rfind("preprocessor.", 0) == 0)
      return ours.find(name)->detach().clone();  // a pre-processor the file lacks starts as the identity
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
  // Every weight of the file lands somewhere, or the run says which would be lost: a model with a
  // pre-processor given to a config without one must not lose it silently. (--reinit inversion
  // replaces the first stage on purpose.)
  std::vector<std::string> dropped;
  for (const auto& items : {theirs, their_buffers})
    for (const auto& kv : items)
      if (!taken.count(kv.key()) && !(part == GeneratorPart::enhancer && first_stage(kv.key())))
        dropped.push_back(kv.key());
  if (!dropped.empty())
    throw Error(model, "has " + std::to_string(dropped.size()) + " weights this config's model has no place for ('" +
                           printable(dropped.front()) + "'" + (dropped.size() > 1 ? ", ..." : "") +
                           "): its architecture differs (model.preprocessor, model.input, model.enhancer); set the "
                           "same model settings as the file's (flatnet info " +
                           model.string() + ")");
}

void transfer_inversion(const std::filesystem::path& source, const CalibrationPair& c, double lambda, Generator& g) {
  require(lambda > 0 && std::isfinite(lambda), model_key(&ModelSpec::inversion_lambda), "must be positive");
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
  require(old_l->size(2) == k, source,
          "its inversion is " + std::string(k == 1 ? "per channel" : "shared") +
              ", this config's is not (model.inversion.shared)");
  shared_channel = channel_index(m.spec.inversion_channel);
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
  detail::fill_module(
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
