#pragma once
// The reconstruction methods flatnet knows, in one registry: each is a name, what it reconstructs
// from, the spec's settings it reads, the report's label and a factory. `make_reconstructor`
// (recon/reconstructor.hpp), `flatnet recon`'s --method and `flatnet report`'s --methods all read
// it, so a new method is its own file (its factory) and one line in methods.cpp's list, or one
// `register_method` call (a test, a plug-in), and nothing else changes.
#include <deque>
#include <functional>
#include <string>
#include <vector>

#include "recon/reconstructor.hpp"

namespace flatnet {

// What a method reconstructs from: the camera's calibration (a classical solve; `flatnet recon`
// and the report's calibration columns), or a model file (`flatnet infer`; the report's
// NAME=MODEL columns).
enum class MethodInput { calibration, model_file };

struct ReconstructionMethod {
  std::string name;   // as the user types it: "tikhonov"
  std::string label;  // the report's and the logs' name for it: "Tikhonov"
  std::string help;   // one line for --help
  MethodInput input = MethodInput::calibration;
  std::vector<std::string> reads;  // the ReconstructorSpec settings it reads beside the camera ("lambda")
  // A report runs it on only the first report.tv_count captures of a set (seconds per capture).
  bool slow = false;
  // The engine for `spec` (spec.method is this method's name); errors name what is missing or wrong.
  std::function<BuiltReconstructor(const ReconstructorSpec&)> build;
};

// Every registered method, the built-in ones first (tikhonov, tv, flatnet, opencv), then those
// registered later, in order. A registration never moves the methods already there.
const std::deque<ReconstructionMethod>& reconstruction_methods();
// Adds a method. Its name must be new, plain (one path component: the report writes a folder of
// that name) and not "model" (the report's kind for model files), and it must have a factory; else
// an error.
void register_method(ReconstructionMethod method);
// Removes a method registered with register_method (built-in ones stay); for tests, which register
// a method for their own length. References to that method become invalid.
void unregister_method(const std::string& name);
// The method of that name, else nullptr.
const ReconstructionMethod* find_method(const std::string& name);
// The method of that name and input, else an error under `option` that lists the names there are
// ("must be tikhonov or tv, got 'x'").
const ReconstructionMethod& require_method(const std::string& name, MethodInput input, const std::string& option);
// The names of the methods with that input, as a help text lists them: "tikhonov | tv".
std::string method_names(MethodInput input, const std::string& separator = " | ");

}  // namespace flatnet
