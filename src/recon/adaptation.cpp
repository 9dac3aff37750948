#include "recon/adaptation.hpp"

#include <chrono>
#include <cmath>
#include <iomanip>
#include <sstream>

#include "core/error.hpp"
#include "core/util.hpp"
#include "recon/data_consistency.hpp"
#include "nn/fused_adam.hpp"

namespace flatnet {

void check_adaptation_options(const AdaptationOptions& o) {
  require_option(o.steps >= 0 && o.steps <= 10000, "infer.adapt_steps", "0 (off) to 10000 steps");
  require_option(o.batch >= 1 && o.batch <= 64, "infer.adapt_batch", "1 to 64 captures a step");
  require_option(std::isfinite(o.lr) && o.lr > 0 && o.lr <= 1e-2, "infer.adapt_lr", "a rate in (0, 0.01]");
  require_option(std::isfinite(o.anchor) && o.anchor >= 0 && o.anchor <= 1e9, "infer.adapt_anchor",
                 "0 (no pull to the shipped weights) to 1e9");
  require_option(o.captures >= 1 && o.captures <= 256, "infer.adapt_captures", "1 to 256 captures");
  require_option(std::isfinite(o.brightness) && o.brightness >= 0 && o.brightness <= 1e6, "infer.adapt_brightness",
                 "0 (the pictures' brightness free) to 1e6");
}

std::string AdaptationReport::summary() const {
  std::ostringstream s;
  s << "adapted to " << captures << " captures in " << steps << " steps (" << std::fixed << std::setprecision(1)
    << seconds << " s): disagreement with them " << std::setprecision(4) << disagreement_before << " -> "
    << disagreement_after << ", weights moved " << std::setprecision(5) << distance << " of their norm";
  return s.str();
}

std::vector<std::filesystem::path> adaptation_captures(const std::vector<std::filesystem::path>& all,
                                                       const AdaptationOptions& o) {
  const auto n = static_cast<int64_t>(all.size());
  if (n <= o.captures) return all;
  std::vector<std::filesystem::path> chosen;
  for (int64_t k = 0; k < o.captures; ++k) chosen.push_back(all[static_cast<size_t>(k * n / o.captures)]);
  return chosen;
}

namespace {

// One pass over all the captures without gradients: (1)'s first term, their mean, and each
// picture's mean value {n} (what the brightness term holds).
struct Pictures {
  double disagreement = 0;
  torch::Tensor means;
};
Pictures look_at(Generator& generator, const std::vector<torch::Tensor>& planes, const DataConsistency& measure,
                 int64_t batch) {
  torch::NoGradGuard no_grad;
  double sum = 0;
  std::vector<torch::Tensor> means;
  for (size_t first = 0; first < planes.size(); first += static_cast<size_t>(batch)) {
    const auto last = std::min(planes.size(), first + static_cast<size_t>(batch));
    const auto Y = torch::stack(std::vector<torch::Tensor>(planes.begin() + first, planes.begin() + last));
    const auto picture = generator->forward(Y);
    sum += measure.disagreement(Y, picture).sum().item<double>();
    means.push_back(picture.to(torch::kFloat32).mean({1, 2, 3}));
  }
  return {sum / static_cast<double>(planes.size()), torch::cat(means).clamp_min(1e-3)};
}

}  // namespace

AdaptationReport adapt_to_captures(Generator& generator, const std::vector<torch::Tensor>& planes,
                                   const DataConsistency& measure, const AdaptationOptions& o) {
  check_adaptation_options(o);
  require(!planes.empty(), "infer", "test-time adaptation needs at least one capture");
  const auto start = std::chrono::steady_clock::now();
  generator->eval();  // running batch-norm statistics: a few captures have none of their own
  generator->set_autocast_bf16(o.bf16);
  AdaptationReport report;
  report.captures = static_cast<int64_t>(planes.size());
  const auto before = look_at(generator, planes, measure, o.batch);
  report.disagreement_before = before.disagreement;
  const auto& shipped_means = before.means;  // {n}
  std::vector<torch::Tensor> params, shipped;
  double shipped_norm2 = 0;
  // The enhancer alone: the first stage is the camera's own inversion, and fitted to a few captures it
  // learns their noise as row and column stripes (the whole model, 30 steps at 1e-4 on the prototype's
  // simulated held-out captures: a grid over every picture).
  for (auto& item : generator->named_parameters()) {
    auto& p = item.value();
    if (!p.requires_grad() || item.key().rfind("enhancer.", 0) != 0) continue;
    params.push_back(p);
    shipped.push_back(p.detach().clone());
    shipped_norm2 += p.detach().square().sum().item<double>();
  }
  shipped_norm2 = std::max(shipped_norm2, 1e-30);
  FusedAdam adam(params, torch::optim::AdamOptions(o.lr));
  Progress progress("adapt", o.steps);
  const auto n = static_cast<int64_t>(planes.size());
  for (int64_t step = 0; step < o.steps; ++step) {
    std::vector<torch::Tensor> batch;
    std::vector<int64_t> index;
    for (int64_t k = 0; k < std::min(o.batch, n); ++k) {
      index.push_back((step * o.batch + k) % n);
      batch.push_back(planes[static_cast<size_t>(index.back())]);
    }
    const auto Y = torch::stack(batch);  // {b,4,rows,cols}
    const auto picture = generator->forward(Y);
    auto loss = measure.disagreement(Y, picture).mean();
    if (o.brightness > 0) {  // (1)'s brightness term: the capture holds no level, the shipped picture's is kept
      const auto target = shipped_means.index({torch::tensor(index)});
      loss = loss + o.brightness * (picture.to(torch::kFloat32).mean({1, 2, 3}) / target - 1).square().mean();
    }
    if (o.anchor > 0) {
      auto drift = torch::zeros({}, torch::kFloat32);
      for (size_t i = 0; i < params.size(); ++i) drift = drift + (params[i] - shipped[i]).square().sum();
      loss = loss + (o.anchor / shipped_norm2) * drift;
    }
    require(std::isfinite(loss.item<double>()), "infer",
            "test-time adaptation's loss is not finite at step " + std::to_string(step) +
                ": lower --adapt-lr or give captures of this camera");
    adam.zero_grad();
    loss.backward();
    adam.step();
    std::ostringstream status;
    status << "loss " << std::setprecision(4) << loss.item<double>();
    progress.set_status(status.str());
    progress.tick();
  }
  progress.finish();
  report.steps = o.steps;
  report.disagreement_after = look_at(generator, planes, measure, o.batch).disagreement;
  double moved2 = 0;
  for (size_t i = 0; i < params.size(); ++i) moved2 += (params[i].detach() - shipped[i]).square().sum().item<double>();
  report.distance = std::sqrt(moved2 / shipped_norm2);
  generator->set_autocast_bf16(false);
  report.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return report;
}

}  // namespace flatnet
