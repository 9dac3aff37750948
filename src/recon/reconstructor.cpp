#include "recon/reconstructor.hpp"

#include <functional>
#include <iomanip>
#include <iostream>
#include <sstream>

#include <opencv2/core/version.hpp>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"
#include "nn/model_file.hpp"
#include "recon/data_consistency.hpp"
#include "recon/opencv_engine.hpp"
#include "recon/tikhonov.hpp"

namespace flatnet {

namespace {

std::string short_number(double x) {
  std::ostringstream s;
  s << std::setprecision(3) << x;
  return s.str();
}

// Tikhonov or TV: the camera's light level removed (its centring), a linear solve per plane, the
// primaries unmixed where the camera's planes see a mix of them, then sRGB.
class ClassicalReconstructor final : public Reconstructor {
 public:
  using Solve = std::function<torch::Tensor(const torch::Tensor&)>;  // {B,4,h,w} -> {B,4,N,N}
  ClassicalReconstructor(Solve solve, std::string description, const CameraConfig& camera, const Calibration& calib)
      : solve_(std::move(solve)),
        description_(std::move(description)),
        fixed_light_(calib.fixed_light.defined() ? calib.fixed_light.to(torch::kFloat32) : torch::Tensor()),
        centring_(camera.raw.centring),
        display_gamma_(camera.display_gamma),
        mix_(camera.colour_mix.empty() ? torch::Tensor() : colour_mix_matrix(camera.colour_mix)) {}
  std::string describe() const override { return description_; }
  torch::Tensor reconstruct(const torch::Tensor& planes) override {
    // The capture less its level and the light it holds whatever the scene: Y = F + P X Q^T.
    const auto X = solve_(without_fixed_light(without_level(planes, centring_), fixed_light_));  // {B,4,N,N}
    const auto rgb = mix_.defined() ? unmix_primaries(X, mix_) : bayer_planes_to_rgb(X);
    return light_to_display(rgb, display_gamma_);  // {B,3,N,N}
  }

 private:
  Solve solve_;
  std::string description_;
  torch::Tensor fixed_light_;  // {4,h,w} or undefined
  Centring centring_;
  double display_gamma_;
  torch::Tensor mix_;  // {4,3} or undefined
};

class FlatNetReconstructor final : public Reconstructor {
 public:
  FlatNetReconstructor(Generator generator, const InferenceLevers& levers, std::string name)
      : generator_(std::move(generator)), name_(std::move(name)), bf16_(levers.bf16) {
    generator_->prepare_inference(levers);
  }
  std::string describe() const override { return name_ + (bf16_ ? " (bf16)" : " (fp32)"); }
  torch::Tensor reconstruct(const torch::Tensor& planes) override {
    c10::InferenceMode no_grad;
    return generator_->forward(planes);  // {B,4,rows,cols} -> {B,3,N,N}
  }

 private:
  Generator generator_;
  std::string name_;
  bool bf16_;
};

class OpenCvReconstructor final : public Reconstructor {
 public:
  explicit OpenCvReconstructor(const std::filesystem::path& onnx_file) : engine_(onnx_file), path_(onnx_file) {}
  OpenCvEngine& engine() { return engine_; }
  std::string describe() const override {
    return "ONNX " + path_.filename().string() + " through OpenCV DNN " + CV_VERSION + " (fp32)";
  }
  torch::Tensor reconstruct(const torch::Tensor& planes) override { return engine_.forward(planes); }

 private:
  OpenCvEngine engine_;
  std::filesystem::path path_;
};

}  // namespace

std::string classical_method_name(ClassicalMethod method) {
  return method == ClassicalMethod::tikhonov ? "tikhonov" : "tv";
}

std::unique_ptr<Reconstructor> make_classical(const Calibration& calib, const CameraConfig& camera,
                                              const ClassicalOptions& o) {
  if (o.method == ClassicalMethod::tikhonov) {
    auto tik = std::make_shared<const Tikhonov>(calib, o.lambda > 0 ? o.lambda : camera.tikhonov_lambda);
    return std::make_unique<ClassicalReconstructor>([tik](const torch::Tensor& y) { return (*tik)(y); },
                                                    "Tikhonov (lambda " + short_number(tik->lambda()) + ")", camera,
                                                    calib);
  }
  TVOptions tv;
  tv.lambda = o.lambda > 0 ? o.lambda : camera.tv_lambda;
  tv.tikhonov_lambda = camera.tikhonov_lambda;
  auto solver = std::make_shared<const TVSolver>(calib, tv);
  return std::make_unique<ClassicalReconstructor>([solver](const torch::Tensor& y) { return (*solver)(y); },
                                                  "TV (lambda " + short_number(tv.lambda) + ")", camera, calib);
}

std::unique_ptr<Reconstructor> make_flatnet(Generator generator, const CameraConfig& camera,
                                            const InferenceLevers& levers, const std::string& name) {
  check_camera_for_model(generator->options(), camera);
  return std::make_unique<FlatNetReconstructor>(std::move(generator), levers, name);
}

std::unique_ptr<Reconstructor> make_opencv(const std::filesystem::path& onnx_file, const CameraConfig& camera) {
  auto r = std::make_unique<OpenCvReconstructor>(onnx_file);
  r->engine().check_camera(camera);
  return r;
}

namespace {

// Why this camera's captures cannot be judged, or "" when they can: no noise model, or a window too
// small beside the scene to measure anything outside the calibration's span (not an error: such a
// camera reconstructs, unjudged; --require-fit then refuses, naming this). Checked before any
// calibration is read.
std::string no_fit_reason(const CameraConfig& camera) {
  if (!camera.knows_noise())
    return "camera '" + camera.name + "' has no noise model (noise_gain; flatnet calibrate --dataset measures it)";
  if (!camera_fit_measurable(camera.raw.crop[2], camera.raw.crop[3], camera.scene_size))
    return "camera '" + camera.name + "' has a window (" + std::to_string(camera.raw.crop[2]) + "x" +
           std::to_string(camera.raw.crop[3]) + ") too small beside its " + std::to_string(camera.scene_size) +
           "-pixel scene to test a capture's fit";
  return "";
}

// The camera fit for a calibration, or nullptr with `why` set.
std::shared_ptr<const CameraFit> fit_of_calibration(const Calibration& calib, const CameraConfig& camera,
                                                    std::string& why) {
  why = no_fit_reason(camera);
  return why.empty() ? std::make_shared<const CameraFit>(calib, camera) : nullptr;
}

}  // namespace

std::shared_ptr<const CameraFit> camera_fit_of(const CameraConfig& camera, std::string& why) {
  if (camera.calibration.empty() || !std::filesystem::exists(camera.calibration)) {
    why = "camera '" + camera.name + "' names no calibration here";
    return nullptr;
  }
  why = no_fit_reason(camera);
  if (!why.empty()) return nullptr;
  return std::make_shared<const CameraFit>(load_calibration(camera.calibration, camera), camera);
}

namespace {

// The part of `path` after its last component named `folder` (configs/cameras/a/b.yaml, "cameras":
// a/b.yaml); empty when no component is, or when the path climbs with `..` anywhere, so that a
// path read from a file is never moved into flatnet's folders.
std::filesystem::path part_after_last(const std::filesystem::path& path, const std::string& folder) {
  std::filesystem::path after;
  bool found = false;
  for (const auto& part : path) {
    if (part == "..") return {};
    if (part == folder) {
      after.clear();
      found = true;
    } else {
      after /= part;
    }
  }
  return found ? after : std::filesystem::path();
}

// The camera a model was trained with: its file's camera when that names a calibration; else the
// camera file its training config names (data.camera), or, when that path is not on this machine
// (a model trained elsewhere or in another checkout), the same place among flatnet's own cameras
// (configs/cameras) or models (models/stages/identified-camera/, the shipped calibration-free
// model's), then the file of the same name among the cameras: any only when its name and geometry
// are the model's. The recorded path comes from the model file, so it is a hint and nothing more: a
// file there that is not a camera is passed over, and a path with `..` is never moved into
// flatnet's folders.
CameraConfig training_camera(const ModelFile& m) {
  if (!m.camera.calibration.empty()) return m.camera;
  // Whatever lies behind a hint (a link loop, an overlong name, a FIFO, a camera whose calibration
  // holds NaN or is a sparse giant) is passed over with one line, never an error: the hint is optional.
  const auto pass_over = [](const std::filesystem::path& path, const std::string& why) {
    std::cerr << "camera fit: the model's recorded training camera " << printable(path.string())
              << " is passed over: " << printable(why) << "\n";
  };
  const std::filesystem::path recorded = m.recorded_camera();
  if (recorded.empty()) return m.camera;
  std::vector<std::filesystem::path> candidates{recorded};
  try {
    // Where it lies under a `cameras` folder (configs/cameras/flatnet_prototype/camera.yaml), the same
    // place among flatnet's own cameras; under a `models` folder, the same place among its models;
    // then the file name alone.
    const auto own = data_dir() / "configs" / "cameras";
    for (const auto& [folder, mine] : {std::pair{"cameras", own}, std::pair{"models", data_dir() / "models"}}) {
      const auto below = part_after_last(recorded, folder);
      if (!below.empty()) candidates.push_back(mine / below);
    }
    candidates.push_back(own / recorded.filename());
  } catch (const Error&) {  // an installation without its data folder: the recorded path alone
  }
  for (const auto& path : candidates) {
    std::error_code ec;
    if (!std::filesystem::is_regular_file(path, ec)) {
      if (ec && ec != std::errc::no_such_file_or_directory) pass_over(path, ec.message());
      continue;
    }
    CameraConfig cam;
    try {
      cam = load_camera_config(path);
      const bool same = cam.name == m.camera.name && cam.raw.crop == m.camera.raw.crop &&
                        cam.scene_size == m.camera.scene_size && cam.raw.raw_height == m.camera.raw.raw_height &&
                        cam.raw.raw_width == m.camera.raw.raw_width;
      if (!same) continue;
      if (!cam.calibration.empty()) (void)load_calibration(cam.calibration, cam);  // read now: its errors pass it over
      return cam;
    } catch (const std::exception& e) {  // not a camera file, or one whose calibration cannot be read
      pass_over(path, e.what());
    }
  }
  return m.camera;
}

}  // namespace

std::shared_ptr<const CameraFit> model_camera_fit(const ModelFile& model, std::string& why) {
  return camera_fit_of(training_camera(model), why);
}

namespace {

void check_capture_headers(const ReconstructorSpec& spec, const CameraConfig& camera) {
  if (!spec.first_capture.empty()) check_raw_header(spec.first_capture, camera.raw);
}

}  // namespace

DataConsistencyOptions consistency_of(const ReconstructorSpec& spec, const ModelSpec& model) {
  const bool own = spec.data_consistency == ReconstructorSpec::kModelsOwn;
  DataConsistencyOptions o;
  o.strength = own ? model.consistency_strength : spec.data_consistency;
  o.blur = spec.consistency_blur != ReconstructorSpec::kModelsOwn ? spec.consistency_blur
           : model.consistency_strength > 0                       ? model.consistency_blur
                                                                  : 0;
  // One rule with export and train: a blur where no step runs would change nothing, so it is refused.
  require_option(spec.consistency_blur == ReconstructorSpec::kModelsOwn || spec.consistency_blur == 0 || o.strength > 0,
                 "infer.consistency_blur",
                 "blurs the data-consistency step's correction, and no step runs here (the model applies none "
                 "and " +
                     option_key("infer.data_consistency") +
                     " is off or not given): give a strength too, or leave the blur out");
  return o;
}

namespace {

// The measurement through the camera's calibration that data consistency and test-time adaptation
// share: the given camera's, else the model's training camera's (named when neither is here).
std::shared_ptr<const DataConsistency> measurement_of(const ReconstructorSpec& spec, const ModelFile& m,
                                                      const CameraConfig& camera, DataConsistencyOptions o) {
  const auto own = spec.use_camera && !spec.camera.calibration.empty() ? spec.camera : training_camera(m);
  require_option(!own.calibration.empty(), o.strength > 0 ? "infer.data_consistency" : "infer.adapt_steps",
                 "needs the camera's calibration: the model's training camera is not here (give --camera with a "
                 "camera file that names one)");
  auto dc_camera = own;
  dc_camera.raw.centring = camera.raw.centring;  // the planes arrive preprocessed as the model reads them
  if (o.strength <= 0) o.strength = DataConsistencyOptions{}.strength;  // adaptation's measure alone
  return std::make_shared<const DataConsistency>(load_calibration(own.calibration, own), dc_camera, o);
}

// Test-time adaptation of the loaded model to spec.adapt_on (before it is prepared for inference).
std::string adapt_model(const ReconstructorSpec& spec, ModelFile& m, const CameraConfig& camera,
                        const DataConsistency& measure) {
  std::vector<torch::Tensor> planes;
  for (const auto& path : adaptation_captures(spec.adapt_on, spec.adapt))
    planes.push_back(load_capture(path, camera.raw).planes);  // {4,rows,cols}
  return adapt_to_captures(m.generator, planes, measure, spec.adapt).summary();
}

}  // namespace

BuiltReconstructor build_flatnet(const ReconstructorSpec& spec) {
  auto m = load_model_file(spec.model);
  const auto camera = spec.use_camera ? spec.camera : m.camera;
  check_capture_headers(spec, camera);
  const auto consistency = consistency_of(spec, m.spec);
  const bool corrects = consistency.strength > 0;
  const auto measure = corrects || spec.adapt.steps > 0 ? measurement_of(spec, m, camera, consistency) : nullptr;
  const auto adaptation = spec.adapt.steps > 0 ? adapt_model(spec, m, camera, *measure) : std::string();
  BuiltReconstructor built{make_flatnet(m.generator, camera, spec.levers, "FlatNet " + spec.model.filename().string()),
                           camera, nullptr, ""};
  built.adaptation = adaptation;
  built.fit = model_camera_fit(m, built.no_fit);
  if (corrects) built.engine = with_data_consistency(std::move(built.engine), measure);
  built.corrected = corrects;
  if (spec.levers.self_ensemble && m.spec.inversion_init == "calibfree")
    built.warning =
        "the self-ensemble assumes an enhancer that works the same on a flipped image; a first stage started from "
        "pseudo-random Toeplitz matrices shifts the scene and its enhancer undoes the shift, so flips hurt it (such "
        "a model: -1.24 dB on the held-out set, docs/evaluation.md)";
  return built;
}

BuiltReconstructor build_classical(const ReconstructorSpec& spec, ClassicalMethod method) {
  check_capture_headers(spec, spec.camera);
  std::shared_ptr<const Calibration> calib = spec.loaded_calibration;
  if (!calib) {
    const auto calib_path = spec.calibration.empty() ? spec.camera.calibration : spec.calibration;
    require_option(!calib_path.empty(), "recon.calib", "no calibration: pass one, or use a camera file that names one");
    calib = std::make_shared<const Calibration>(load_calibration(calib_path, spec.camera));
  }
  BuiltReconstructor built{make_classical(*calib, spec.camera, {method, spec.lambda}), spec.camera, nullptr, ""};
  built.fit = fit_of_calibration(*calib, spec.camera, built.no_fit);
  return built;
}

BuiltReconstructor build_opencv(const ReconstructorSpec& spec) {
  auto r = std::make_unique<OpenCvReconstructor>(spec.model);
  const auto camera = spec.use_camera ? spec.camera : r->engine().camera();
  r->engine().check_camera(camera);
  check_capture_headers(spec, camera);
  BuiltReconstructor built{std::move(r), camera, nullptr, "an ONNX file carries no calibration to judge by"};
  built.fit = camera_fit_of(camera, built.no_fit);  // the camera given, or the ONNX file's own
  return built;
}

}  // namespace flatnet
