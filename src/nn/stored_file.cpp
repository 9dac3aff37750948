#include "nn/stored_file.hpp"

#include <chrono>
#include <set>
#include <ctime>
#include <iomanip>
#include <set>
#include <sstream>

#include "core/error.hpp"
#include "core/precision.hpp"
#include "core/util.hpp"
#include "io/safetensors.hpp"
#include "io/torch_file.hpp"

namespace flatnet::detail {

const std::string& Stored::text(const std::string& key, const std::filesystem::path& path) const {
  const auto it = meta.find(key);
  if (it == meta.end()) throw Error(path, "not a flatnet file (no '" + key + "' in it)");
  return it->second;
}

std::map<std::string, torch::Tensor> Stored::under(const std::string& prefix) const {
  std::map<std::string, torch::Tensor> out;
  for (const auto& [name, t] : tensors)
    if (name.rfind(prefix + ".", 0) == 0) out[name.substr(prefix.size() + 1)] = t;
  return out;
}

void fill_module(torch::nn::Module& m, const std::filesystem::path& where, const std::string& label,
                 const std::function<torch::Tensor(const std::string&, bool)>& fetch,
                 const std::function<std::string(const std::string&)>& name_in_file) {
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
  std::set<std::string> used;
  fill_module(m, where, key + " weight", [&](const std::string& name, bool) {
    const auto it = tensors.find(name);
    if (it == tensors.end())
      throw Error(where, key + " weights lack '" + name + "' (the file's architecture differs from its config)");
    used.insert(name);
    return it->second;
  });
  // A weight the model has no place for would be dropped silently (a spec saying `input: tikhonov`
  // over a trained inversion's weights runs Tikhonov): the file's spec and weights disagree.
  for (const auto& [name, t] : tensors)
    if (!used.count(name))
      throw Error(where,
                  key + " weight '" + printable(name) +
                      "' has no place in the model its stored spec describes (the spec and the weights disagree: "
                      "a damaged or edited file?)");
}

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
    expect("enhancer.outc.conv.weight", 1, spec.unet_width, model_key(&ModelSpec::unet_width));
  if (spec.enhancer == "dncnn") {
    expect("enhancer.body.0.weight", 0, spec.dncnn_width, "model.dncnn.width");
    require(spec.dncnn_layers <= count, path, "model.dncnn.layers exceeds the weights the file holds");
  }
  if (spec.enhancer == "rcan") {
    expect("enhancer.head.weight", 0, spec.rcan_width, "model.rcan.width");
    require(spec.rcan_groups * spec.rcan_blocks <= count, path,
            "model.rcan.groups x blocks exceeds the weights the file holds");
  }
  if (spec.enhancer == "nafnet") {
    expect("enhancer.intro.weight", 0, spec.nafnet_width, "model.nafnet.width");
    require(4 * (spec.nafnet_enc_blocks + spec.nafnet_dec_blocks) + spec.nafnet_middle_blocks <= count, path,
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
