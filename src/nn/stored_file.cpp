#include "nn/stored_file.hpp"

#include <set>
#include <iomanip>
#include <set>
#include <sstream>

#include "core/error.hpp"
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
  auto archive = read_archive_top_level(path);  // one pass over the archive, as data
  Stored s;
  s.version = 1;
  for (auto& [key, text] : archive.text) s.meta[key == "flatnet_format" ? "format" : key] = text;
  if (const auto it = archive.integers.find("step"); it != archive.integers.end())
    s.meta["step"] = std::to_string(it->second);
  if (const auto it = archive.reals.find("best_psnr"); it != archive.reals.end())
    s.meta["best_psnr"] = format_number(it->second);
  s.tensors = std::move(archive.tensors);
  for (const char* module : {"generator", "generator_ema", "discriminator"})
    if (const auto it = archive.tensor_dicts.find(module); it != archive.tensor_dicts.end())
      for (auto& [name, t] : it->second) s.tensors[std::string(module) + "." + name] = t;
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

}  // namespace flatnet::detail
