#include "nn/model_record.hpp"

#include <chrono>
#include <ctime>

#include "core/error.hpp"
#include "core/precision.hpp"
#include "core/util.hpp"

namespace flatnet::detail {

namespace {

std::string utc_now_iso8601() {
  const auto now = std::chrono::system_clock::to_time_t(std::chrono::system_clock::now());
  std::tm utc{};
  gmtime_r(&now, &utc);
  char text[32];
  std::strftime(text, sizeof text, "%Y-%m-%dT%H:%M:%SZ", &utc);
  return text;
}

}  // namespace

std::map<std::string, std::string> header(const std::string& format, const ModelIdentity& identity) {
  std::map<std::string, std::string> meta{{"format", format},
                                          {"format_version", std::to_string(kFormatVersion)},
                                          {"model_spec", model_spec_yaml(identity.spec)},
                                          {"config", identity.config_yaml},
                                          {"camera", camera_geometry_yaml(identity.camera)},
                                          {"written_by", std::string("flatnet ") + FLATNET_VERSION}};
  auto provenance = identity.provenance;
  provenance.written_at = utc_now_iso8601();
  provenance.written_on = cpu_features().summary();
  provenance.consistency = consistency_origin(identity.spec, provenance);
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

namespace {

// The sizes a spec claims, checked against the weights the file holds before a network of that
// size is built: a hostile spec (width 4096, scene 4194304) would otherwise allocate gigabytes
// first. Each size-setting option is pinned by one tensor's shape; depths (layers, blocks) are
// bounded by the number of tensors present (each layer holds at least one).
void check_sizes_against_weights(const ModelSpec& spec, const CameraConfig& camera, const Stored& s,
                                 const std::filesystem::path& path) {
  const auto g = s.under("generator");
  auto expect = [&](const std::string& name, int64_t dim, int64_t value, const std::string& option) {
    const auto it = g.find(name);
    require(it != g.end(), path, "has no generator weight '" + name + "' (its spec says " + option + ")");
    require(it->second.dim() > dim && it->second.size(dim) == value, path,
            option + " = " + std::to_string(value) + " disagrees with the weights (generator '" + name + "' is " +
                c10::str(it->second.sizes()) + ")");
  };
  const int64_t rows = camera.raw.crop[2], cols = camera.raw.crop[3], n = camera.scene_size;
  if (parse_input_stage(spec.input) == InputStage::inversion) {
    expect("inversion.PhiL", 0, rows, "camera crop height");
    expect("inversion.PhiL", 1, n, "camera scene_size");
    expect("inversion.PhiR", 0, cols, "camera crop width");
  } else {
    expect("tikhonov.ULt", 1, n, "camera scene_size");
    expect("tikhonov.ULt", 2, rows, "camera crop height");
    expect("tikhonov.UR", 1, cols, "camera crop width");
  }
  const auto count = static_cast<int64_t>(g.size());
  if (spec.enhancer == "unet")
    expect("enhancer.outc.conv.weight", 1, spec.unet.width, model_key<&ModelSpec::unet, &UNetOptions::width>());
  if (spec.enhancer == "dncnn") {
    expect("enhancer.body.0.weight", 0, spec.dncnn.width, model_key<&ModelSpec::dncnn, &DnCNNOptions::width>());
    require(spec.dncnn.layers <= count, path, "model.dncnn.layers exceeds the weights the file holds");
  }
  if (spec.enhancer == "rcan") {
    expect("enhancer.head.weight", 0, spec.rcan.width, model_key<&ModelSpec::rcan, &RCANOptions::width>());
    require(spec.rcan.groups * spec.rcan.blocks <= count, path,
            "model.rcan.groups x blocks exceeds the weights the file holds");
  }
  if (spec.enhancer == "nafnet") {
    expect("enhancer.intro.weight", 0, spec.nafnet.width, model_key<&ModelSpec::nafnet, &NAFNetOptions::width>());
    require(4 * (spec.nafnet.enc_blocks + spec.nafnet.dec_blocks) + spec.nafnet.middle_blocks <= count, path,
            "model.nafnet block counts exceed the weights the file holds");
  }
}

}  // namespace

std::pair<ModelSpec, CameraConfig> stored_model(const Stored& s, const std::filesystem::path& path) {
  const auto stored_spec = s.meta.find("model_spec");
  auto spec = stored_spec != s.meta.end() ? parse_model_spec(stored_spec->second, path, /*strict=*/true)
                                          : parse_model_spec(s.text("config", path), path, /*strict=*/false);
  auto camera = camera_from_yaml_text(s.text("camera", path), path);
  // A bench is a simulated camera's truth, for simulation only: flatnet never writes one into a model.
  require(!camera.bench.any(), path,
          "its camera carries a bench: section (simulated bench errors); a model file never does: not a file "
          "flatnet wrote, or one edited by hand");
  check_sizes_against_weights(spec, camera, s, path);
  // A step the model applies must fit its own scenes (model_spec's 0-64 allows more than a small
  // camera holds): refused here, naming the file, rather than at inference naming a setting.
  if (spec.consistency_strength > 0) {
    const auto reach = consistency_blur_reach_problem(spec.consistency_blur, camera.scene_size);
    require(reach.empty(), path, "its data-consistency step (model.consistency.blur): " + reach);
  }
  return {spec, camera};
}

ModelFile read_generator(const Stored& s, const std::filesystem::path& path, bool* used_average) {
  auto [spec, camera] = stored_model(s, path);
  ModelFile m;
  m.generator = Generator(generator_options(spec, camera, false));
  m.spec = spec;
  m.camera = camera;
  m.recipe = s.text("config", path);
  m.recipe_values = flat_yaml(m.recipe, path);
  m.format_version = s.version;
  m.provenance = provenance_of(s);
  const auto& origin = m.provenance.consistency;
  require(origin.empty() || origin == kConsistencyTrained || origin == kConsistencySetAtExport, path,
          "its record's consistency is '" + printable(origin) + "'; flatnet writes '" + kConsistencyTrained + "' or '" +
              kConsistencySetAtExport + "' (not a file flatnet wrote, or one edited by hand)");
  m.provenance.consistency = consistency_origin(spec, m.provenance);
  const bool checkpoint = s.text("format", path) == kCheckpointFormat;
  const bool average = checkpoint && !s.under("generator_ema").empty();
  if (checkpoint) {  // what a model exported from it will say
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

}  // namespace flatnet::detail
