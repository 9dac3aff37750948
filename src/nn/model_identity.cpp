#include "nn/model_identity.hpp"

namespace flatnet {

ModelIdentity model_identity(const Config& config, const CameraConfig& camera) {
  return {config.to_yaml(), model_spec(config), camera, {}};
}

ModelIdentity model_identity(const ModelFile& m) { return {m.recipe, m.spec, m.camera, m.provenance}; }

std::string ModelFile::recorded(const std::string& key) const {
  const auto it = recipe_values.find(key);
  return it == recipe_values.end() ? "" : it->second;
}

// The training config's camera key (train/options' data table; a model file is read below that layer).
std::filesystem::path ModelFile::recorded_camera() const { return recorded("data.camera"); }

std::vector<std::pair<std::string, std::string Provenance::*>> provenance_fields() {
  return {{"trained_steps", &Provenance::trained_steps},
          {"train_seconds", &Provenance::train_seconds},
          {"best_val_psnr", &Provenance::best_val_psnr},
          {"written_at", &Provenance::written_at},
          {"written_on", &Provenance::written_on},
          {"source", &Provenance::source},
          {"scores", &Provenance::scores},
          {"consistency", &Provenance::consistency}};
}

std::string consistency_origin(const ModelSpec& spec, const Provenance& provenance) {
  if (spec.consistency_strength <= 0) return "";
  if (!provenance.consistency.empty()) return provenance.consistency;
  const bool legacy_export = provenance.source.find("set at export, not trained with") != std::string::npos;
  return legacy_export ? kConsistencySetAtExport : kConsistencyTrained;
}

}  // namespace flatnet
