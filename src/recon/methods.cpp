#include "recon/methods.hpp"

#include <algorithm>
#include <mutex>

#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet {

namespace {

// The built-in methods. A new one: its factory in its own file (declared in recon/reconstructor.hpp
// beside these) and one line here.
std::vector<ReconstructionMethod> builtin_methods() {
  const auto classical = [](ClassicalMethod m) {
    return [m](const ReconstructorSpec& spec) { return build_classical(spec, m); };
  };
  return {
      {"tikhonov",
       "Tikhonov",
       "Tikhonov on the calibration (thesis eq. 2.6)",
       MethodInput::calibration,
       {"calibration", "lambda"},
       false,
       classical(ClassicalMethod::tikhonov)},
      {"tv",
       "TV",
       "total variation (FISTA) on the calibration, seconds per capture",
       MethodInput::calibration,
       {"calibration", "lambda"},
       true,
       classical(ClassicalMethod::tv)},
      {"flatnet",
       "FlatNet",
       "a FlatNet model file through LibTorch",
       MethodInput::model_file,
       {"model", "levers", "data_consistency", "consistency_blur", "adapt", "adapt_on"},
       false,
       build_flatnet},
      {"opencv",
       "FlatNet (ONNX)",
       "an ONNX file from `flatnet export --onnx` through OpenCV DNN",
       MethodInput::model_file,
       {"model"},
       false,
       build_opencv},
  };
}

std::mutex registry_mutex;

// A deque: a registration never moves the methods already there, so references stay valid.
std::deque<ReconstructionMethod>& registry() {
  static std::deque<ReconstructionMethod> methods = [] {
    const auto builtin = builtin_methods();
    return std::deque<ReconstructionMethod>(builtin.begin(), builtin.end());
  }();
  return methods;
}

// The method of that name in `methods`, else nullptr (the caller holds the lock).
const ReconstructionMethod* find_in(const std::deque<ReconstructionMethod>& methods, const std::string& name) {
  for (const auto& m : methods)
    if (m.name == name) return &m;
  return nullptr;
}

std::string or_list(const std::vector<std::string>& names) {
  std::string out;
  for (size_t i = 0; i < names.size(); ++i) out += (i == 0 ? "" : i + 1 == names.size() ? " or " : ", ") + names[i];
  return out;
}

std::vector<std::string> names_of(MethodInput input) {
  std::vector<std::string> names;
  for (const auto& m : reconstruction_methods())
    if (m.input == input) names.push_back(m.name);
  return names;
}

}  // namespace

const std::deque<ReconstructionMethod>& reconstruction_methods() {
  std::lock_guard<std::mutex> lock(registry_mutex);
  return registry();
}

void register_method(ReconstructionMethod method) {
  require_plain_name(method.name, "a reconstruction method's name");
  require(method.name != "model", "register_method", "'model' is the report's kind for model files");
  require(static_cast<bool>(method.build), "register_method", "method '" + method.name + "' has no factory");
  std::lock_guard<std::mutex> lock(registry_mutex);
  require(find_in(registry(), method.name) == nullptr, "register_method",
          "a method named '" + method.name + "' exists");
  registry().push_back(std::move(method));
}

void unregister_method(const std::string& name) {
  std::lock_guard<std::mutex> lock(registry_mutex);
  const auto builtin = builtin_methods().size();
  auto& methods = registry();
  const auto it = std::find_if(methods.begin() + static_cast<std::ptrdiff_t>(builtin), methods.end(),
                               [&](const ReconstructionMethod& m) { return m.name == name; });
  if (it != methods.end()) methods.erase(it);
}

const ReconstructionMethod* find_method(const std::string& name) {
  std::lock_guard<std::mutex> lock(registry_mutex);
  return find_in(registry(), name);
}

const ReconstructionMethod& require_method(const std::string& name, MethodInput input, const std::string& option) {
  const auto* method = find_method(name);
  if (method == nullptr || method->input != input)
    throw Error(option_key(option), "must be " + or_list(names_of(input)) + ", got '" + printable(name) + "'");
  return *method;
}

std::string method_names(MethodInput input, const std::string& separator) {
  std::string out;
  for (const auto& name : names_of(input)) out += (out.empty() ? "" : separator) + name;
  return out;
}

BuiltReconstructor make_reconstructor(const ReconstructorSpec& spec) {
  const auto* method = find_method(spec.method);
  if (method == nullptr) {
    std::vector<std::string> all;
    for (const auto& m : reconstruction_methods()) all.push_back(m.name);
    throw Error(option_key("recon.method"), "must be " + or_list(all) + ", got '" + printable(spec.method) + "'");
  }
  return method->build(spec);
}

}  // namespace flatnet
