#include "train/trainer_checkpoint.hpp"

#include <iomanip>
#include <sstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "nn/optimizer_state.hpp"
#include "train/run_id.hpp"

namespace flatnet {

namespace {

std::string state_key(const torch::Tensor& p) { return c10::guts::to_string(p.unsafeGetTensorImpl()); }

// The stored tensor `name`, shaped like `like` and finite, or an Error naming the checkpoint.
torch::Tensor stored_like(const SafeTensors& st, const std::string& name, const torch::Tensor& like,
                          const std::filesystem::path& path, const std::string& size_hint) {
  const auto* t = st.find(name);
  require(t != nullptr, path, "lacks '" + name + "' (not a checkpoint of this trainer?)");
  require(t->sizes() == like.sizes(), path,
          "'" + name + "' is " + c10::str(t->sizes()) + ", this run's " + c10::str(like.sizes()) +
              (size_hint.empty() ? "" : " (" + size_hint + ")"));
  require(t->is_floating_point() && torch::isfinite(*t).all().item<bool>(), path,
          "'" + name + "' holds NaN or infinity, or is not a floating-point tensor");
  return t->to(like.scalar_type()).clone();
}

void restore_optimizer_state(const SafeTensors& st, const TrainerState& state, const std::string& name,
                             const torch::Tensor& p, const std::filesystem::path& path) {
  const auto base = "optimizer." + name + ".";
  auto& slots = state.optimizer->state();
  slots.erase(state_key(p));
  if (state.optimizer_kind == "sgd") {
    if (!st.find(base + "momentum_buffer")) return;  // no step taken yet
    auto s = std::make_unique<torch::optim::SGDParamState>();
    s->momentum_buffer(stored_like(st, base + "momentum_buffer", p, path, state.size_hint));
    slots[state_key(p)] = std::move(s);
    return;
  }
  const auto* step = st.find(base + "step");
  if (!step) return;
  require(step->numel() == 1 && step->scalar_type() == torch::kInt64 && step->item<int64_t>() >= 0, path,
          "'" + base + "step' is not one non-negative integer");
  auto s = std::make_unique<torch::optim::AdamParamState>();
  s->step(step->item<int64_t>());
  s->exp_avg(stored_like(st, base + "exp_avg", p, path, state.size_hint));
  s->exp_avg_sq(stored_like(st, base + "exp_avg_sq", p, path, state.size_hint));
  require_adam_moments(s->step(), s->exp_avg(), s->exp_avg_sq(), path, base);
  slots[state_key(p)] = std::move(s);
}

}  // namespace

void write_trainer_checkpoint(const std::filesystem::path& path, const TrainerState& state, int64_t step,
                              double seconds, const std::map<std::string, std::string>& metadata,
                              const std::vector<std::pair<std::string, torch::Tensor>>& extra) {
  std::vector<std::pair<std::string, torch::Tensor>> tensors;
  for (const auto& [name, p] : state.params) {
    tensors.emplace_back("param." + name, p.detach());
    const auto it = state.optimizer->state().find(state_key(p));
    if (it == state.optimizer->state().end()) continue;  // no step taken yet
    const auto base = "optimizer." + name + ".";
    if (state.optimizer_kind == "sgd") {
      const auto& s = static_cast<const torch::optim::SGDParamState&>(*it->second);
      if (s.momentum_buffer().defined()) tensors.emplace_back(base + "momentum_buffer", s.momentum_buffer());
    } else {
      const auto& s = static_cast<const torch::optim::AdamParamState&>(*it->second);
      tensors.emplace_back(base + "step", torch::tensor(s.step(), torch::kInt64));
      tensors.emplace_back(base + "exp_avg", s.exp_avg());
      tensors.emplace_back(base + "exp_avg_sq", s.exp_avg_sq());
    }
  }
  for (const auto& t : extra) tensors.push_back(t);
  auto meta = metadata;
  std::ostringstream secs;
  secs << std::setprecision(17) << seconds;
  meta["format"] = state.format;
  meta["step"] = std::to_string(step);
  meta["train_seconds"] = secs.str();
  meta["optimizer"] = state.optimizer_kind;
  if (!state.run_id.empty()) meta["run_id"] = state.run_id;
  write_safetensors(path, tensors, meta);
}

RestoredTraining read_trainer_checkpoint(const std::filesystem::path& path, const TrainerState& state) {
  require(std::filesystem::exists(path), path, "nothing to resume (no checkpoint)");
  RestoredTraining r;
  r.file = read_safetensors(path);
  const auto& st = r.file;
  require(st.meta("format", path) == state.format, path,
          "is not a checkpoint of this trainer (format '" + st.meta("format", path).substr(0, 60) + "', expected '" +
              state.format + "')");
  const auto& kind = st.meta("optimizer", path);
  require(kind == state.optimizer_kind, path,
          "the run trained with train.optimizer " + kind.substr(0, 20) + "; it cannot change to " +
              state.optimizer_kind + " on resume");
  const auto& step_text = st.meta("step", path);
  const auto& seconds_text = st.meta("train_seconds", path);
  require(
      is_decimal_number(step_text) && step_text.find_first_of(".eE-+") == std::string::npos && step_text.size() <= 12,
      path, "step '" + step_text.substr(0, 40) + "' is not a step count");
  require(is_decimal_number(seconds_text) && std::strtod(seconds_text.c_str(), nullptr) >= 0, path,
          "train_seconds '" + seconds_text.substr(0, 40) + "' is not a duration");
  r.step = std::stoll(step_text);
  r.seconds = std::strtod(seconds_text.c_str(), nullptr);
  if (const auto id = st.metadata.find("run_id"); id != st.metadata.end()) {
    require(is_run_id(id->second), path, "run_id is not 16 hex digits");
    r.run_id = id->second;
  }
  torch::NoGradGuard no_grad;
  for (const auto& [name, p] : state.params) {
    const auto value = stored_like(st, "param." + name, p, path, state.size_hint);
    p.copy_(value);
    restore_optimizer_state(st, state, name, p, path);
  }
  return r;
}

}  // namespace flatnet
