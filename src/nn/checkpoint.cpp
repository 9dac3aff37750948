#include "nn/checkpoint.hpp"

#include <cmath>
#include <limits>
#include <sstream>

#include <nlohmann/json.hpp>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/safetensors.hpp"
#include "nn/model_spec.hpp"
#include "nn/optimizer_state.hpp"
#include "nn/model_record.hpp"
#include "nn/stored_file.hpp"

namespace flatnet {

using detail::add_module;
using detail::format_number;
using detail::header;
using detail::kCheckpointFormat;
using detail::load_module;
using detail::read_stored;
using detail::Stored;

namespace {

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
    nlohmann::json g = {{"lr", o.lr()},           {"betas", {std::get<0>(o.betas()), std::get<1>(o.betas())}},
                        {"eps", o.eps()},         {"weight_decay", o.weight_decay()},
                        {"amsgrad", o.amsgrad()}, {"params", nlohmann::json::array()}};
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

// A checkpoint's config (over this flatnet's defaults: a resume continues the run with it), its
// camera, and the discriminator's width checked against its weights before one is built.
std::pair<Config, CameraConfig> training_settings(const Stored& s, const std::filesystem::path& path) {
  auto config = Config::from_text(s.text("config", path), path);
  auto camera = detail::stored_model(s, path).second;
  if (const auto d = s.under("discriminator"); !d.empty()) {
    const auto it = d.find("convs.0.weight");
    require(it != d.end() && it->second.dim() == 4 && it->second.size(0) == discriminator_options(config).width, path,
            discriminator_key(&DiscriminatorOptions::width) + " disagrees with the discriminator's weights");
  }
  return {config, camera};
}

}  // namespace

void save_checkpoint(const std::filesystem::path& path, Generator& g, Discriminator& d, torch::optim::Adam& opt_g,
                     torch::optim::Adam& opt_d, const TrainState& state, const ModelIdentity& identity, Generator* ema,
                     const CheckpointCamera& camera) {
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
  std::tie(out.config, out.camera) = training_settings(s, path);
  out.best_psnr = stored_number(s, "best_psnr", path);
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
  training_settings(s, path);
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

ModelFile model_from_checkpoint(const std::filesystem::path& path, bool* used_average) {
  const auto s = read_stored(path, kCheckpointFormat);
  // The numbers a checkpoint records are checked as --resume checks them: a file whose step or best
  // PSNR is not a number is damaged or edited, and a model exported from it would carry that.
  for (const char* key : {"step", "best_psnr"}) stored_number(s, key, path);
  return detail::read_generator(s, path, used_average);
}

ModelFile load_trained_model(const std::filesystem::path& path) {
  return is_checkpoint_file(path) ? model_from_checkpoint(path) : load_model_file(path);
}

namespace {

// The generator's parameters and buffers, in the order a file stores them (add_module).
std::vector<std::pair<std::string, torch::Tensor>> generator_tensors(Generator& g) {
  std::vector<std::pair<std::string, torch::Tensor>> out;
  add_module(out, "generator", *g);
  return out;
}

std::string strip(const std::string& line) {
  const auto begin = line.find_first_not_of(' ');
  return begin == std::string::npos ? "" : line.substr(begin);
}

// The first line where two YAML texts differ, as "theirs (against ours)"; "" when they are equal.
std::string first_difference(const std::string& ours, const std::string& theirs) {
  std::istringstream a(ours), b(theirs);
  std::string line_a, line_b;
  while (true) {
    const bool more_a = static_cast<bool>(std::getline(a, line_a)), more_b = static_cast<bool>(std::getline(b, line_b));
    if (!more_a && !more_b) return "";
    if (!more_a || !more_b || line_a != line_b) return "'" + strip(line_b) + "' against '" + strip(line_a) + "'";
  }
}

std::string origin_text(const std::string& origin) {
  return origin == kConsistencySetAtExport ? "set at export (its weights trained without it)"
         : origin.empty()                  ? "not at all"
                                           : "its weights were trained with";
}

void require_same_model(const ModelFile& first, const ModelFile& other, const std::filesystem::path& first_path,
                        const std::filesystem::path& path) {
  const auto difference = first_difference(model_spec_yaml(first.spec), model_spec_yaml(other.spec));
  require(difference.empty(), path,
          "holds a different model from " + first_path.string() + " (model spec " + difference +
              "); only models of one spec can be averaged");
  require(camera_geometry_yaml(other.camera) == camera_geometry_yaml(first.camera) &&
              other.camera.name == first.camera.name,
          path,
          "is for another camera than " + first_path.string() + " (camera '" + other.camera.name + "' against '" +
              first.camera.name + "', or another geometry); average models of one camera");
  // The same step in both specs is not the same model when one's weights learned with it and the
  // other's had it added at export: their weights solve different tasks.
  require(other.provenance.consistency == first.provenance.consistency, path,
          "applies the data-consistency step " + origin_text(other.provenance.consistency) + ", " +
              first_path.string() + " " + origin_text(first.provenance.consistency) +
              "; average models whose weights were trained alike");
}

}  // namespace

ModelFile average_models(const std::vector<std::filesystem::path>& paths) {
  require(paths.size() >= 2, "--average-of", "needs at least two model files or checkpoints to average");
  torch::NoGradGuard no_grad;
  ModelFile result;
  std::vector<torch::Tensor> sums;  // float64 sums of the floating tensors, in generator_tensors order
  std::string sources;
  for (size_t i = 0; i < paths.size(); ++i) {
    auto m = load_trained_model(paths[i]);
    auto tensors = generator_tensors(m.generator);
    if (i == 0) {
      for (const auto& t : tensors)
        sums.push_back(t.second.is_floating_point() ? t.second.to(torch::kFloat64) : torch::Tensor());
    } else {
      require_same_model(result, m, paths[0], paths[i]);
      for (size_t k = 0; k < tensors.size(); ++k)
        if (sums[k].defined()) sums[k].add_(tensors[k].second.to(torch::kFloat64));
    }
    sources += (i ? ", " : "") + paths[i].filename().string();
    if (i == 0) {
      result = m;  // fixes the spec and camera every other file must match
    } else if (i + 1 == paths.size()) {
      // The last file's record is kept, and its generator takes the mean (its integer buffers stay).
      result.generator = m.generator;
      result.recipe = m.recipe;
      result.recipe_values = m.recipe_values;
      result.provenance = m.provenance;
    }
  }
  auto target = generator_tensors(result.generator);
  for (size_t k = 0; k < target.size(); ++k)
    if (sums[k].defined()) target[k].second.copy_(sums[k] / static_cast<double>(paths.size()));
  result.provenance.source = "mean of " + std::to_string(paths.size()) + " models: " + sources;
  if (result.provenance.consistency == kConsistencySetAtExport) {  // every file's, as checked above
    std::ostringstream step;
    step << "; data consistency c " << result.spec.consistency_strength << ", blur " << result.spec.consistency_blur
         << " set at export, not trained with";
    result.provenance.source += step.str();
  }
  result.provenance.scores.clear();
  result.generator->eval();
  return result;
}

}  // namespace flatnet
