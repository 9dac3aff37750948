#pragma once
// One interface for every way of turning measurements into a photograph (after LenslessPiCam's
// ReconstructionAlgorithm): classical Tikhonov and TV on the calibration, a FlatNet model through
// LibTorch, or an exported ONNX graph through OpenCV's DNN module. `flatnet recon`, `infer`, `live`,
// `demo`, `report` and the benchmarks all reconstruct through it, and files go through one batch
// loop (recon/batch.hpp).
#include <filesystem>
#include <memory>
#include <string>

#include <torch/torch.h>

#include "io/camera_config.hpp"
#include "optics/camera_fit.hpp"
#include "nn/generator.hpp"
#include "nn/model_file.hpp"
#include "optics/camera.hpp"
#include "recon/adaptation.hpp"

namespace flatnet {

class Reconstructor {
 public:
  virtual ~Reconstructor() = default;
  // One line for logs: "Tikhonov (lambda 0.0003)", "FlatNet model.flatnet (bf16)".
  virtual std::string describe() const = 0;
  // Measurement planes exactly as load_capture / preprocess_raw make them (light level included)
  // {B,4,rows,cols} -> sRGB images {B,3,N,N} in [0,1].
  virtual torch::Tensor reconstruct(const torch::Tensor& planes) = 0;
};

// Tikhonov (thesis eq. 2.6) or TV (FISTA) on the calibration: the camera's light level is removed
// first (its centring), the linear-light planes become sRGB.
enum class ClassicalMethod { tikhonov, tv };
std::string classical_method_name(ClassicalMethod method);  // "tikhonov" | "tv"

struct ClassicalOptions {
  ClassicalMethod method = ClassicalMethod::tikhonov;
  double lambda = 0;  // <= 0: the camera file's default for the method
};
std::unique_ptr<Reconstructor> make_classical(const Calibration& calib, const CameraConfig& camera,
                                              const ClassicalOptions& options);

// A FlatNet generator (it is prepared for inference in place with `levers`); the camera must
// preprocess as the model was trained (check_camera_for_model).
std::unique_ptr<Reconstructor> make_flatnet(Generator generator, const CameraConfig& camera,
                                            const InferenceLevers& levers, const std::string& name = "FlatNet");

// An ONNX file from `flatnet export --onnx`, run by OpenCV's DNN module (fp32, no LibTorch
// kernels); `camera` must preprocess as the graph expects (the file carries its own camera).
std::unique_ptr<Reconstructor> make_opencv(const std::filesystem::path& onnx_file, const CameraConfig& camera);

// Everything a reconstruction engine can be built from, for the factory by name.
struct ReconstructorSpec {
  std::string method = "tikhonov";    // a method's name in recon/methods.hpp's registry
  CameraConfig camera;                // preprocessing; for flatnet and opencv only when use_camera
  bool use_camera = true;             // false: flatnet/opencv use the model file's own camera
  std::filesystem::path calibration;  // tikhonov, tv (empty: the camera's)
  // tikhonov, tv: that calibration already read (a report reads it once for all its columns); null:
  // the factory reads it.
  std::shared_ptr<const Calibration> loaded_calibration;
  double lambda = 0;            // tikhonov, tv (<= 0: the camera's)
  std::filesystem::path model;  // flatnet (.flatnet), opencv (.onnx)
  InferenceLevers levers;       // flatnet
  // flatnet: > 0 corrects each picture by its capture where the calibration resolves it well
  // (recon/data_consistency.hpp, strength c); 0: off; kModelsOwn: the model's own
  // (model.consistency: off for a model trained without it). The calibration is the given camera's,
  // else the model's training camera's.
  static constexpr double kModelsOwn = -1;
  double data_consistency = kModelsOwn;
  double consistency_blur = kModelsOwn;  // sigma of a Gaussian on that correction (scene pixels)
  // flatnet: with adapt.steps > 0 the model is first adapted to these captures (recon/adaptation.hpp),
  // through the same calibration as data consistency.
  AdaptationOptions adapt;
  std::vector<std::filesystem::path> adapt_on;
  // The first capture it will read (optional): its header is checked against the camera (size,
  // depth) before anything the camera's size sets is built (a calibration's SVDs, the camera fit's
  // reference). The rest are checked as each is read.
  std::filesystem::path first_capture;
};

struct BuiltReconstructor {
  std::unique_ptr<Reconstructor> engine;
  CameraConfig camera;  // the preprocessing its input must have (the spec's, or the model's own)
  // Whether a capture fits the camera this engine is for (its calibration, or the camera a model
  // was trained with); null when that camera's calibration or noise model is not known here, and
  // `no_fit` says why.
  std::shared_ptr<const CameraFit> fit;
  std::string no_fit;
  // What the caller should tell the user before reconstructing ("" when nothing): a lever the
  // model is known to suffer from.
  std::string warning = "";
  std::string adaptation = "";  // test-time adaptation's summary ("" when none ran)
  bool corrected = false;       // the pictures pass the data-consistency step (the engine describes it)
};
// The data-consistency step a FlatNet spec asks of a model with `model`'s spec: the model's own
// (model.consistency) where the spec says kModelsOwn, else the spec's; strength 0: none.
struct DataConsistencyOptions;  // recon/data_consistency.hpp
DataConsistencyOptions consistency_of(const ReconstructorSpec& spec, const ModelSpec& model);
// The engine of spec.method, built by that method's factory in the registry (recon/methods.hpp).
// Errors name what is missing or wrong (an unknown method, no calibration, a model file that is
// not one, a camera that does not match the model).
BuiltReconstructor make_reconstructor(const ReconstructorSpec& spec);
// The built-in methods' factories (the registry's entries): Tikhonov or TV on the spec's calibration
// (the camera's when none is given), a FlatNet model file, an ONNX file through OpenCV.
BuiltReconstructor build_classical(const ReconstructorSpec& spec, ClassicalMethod method);
BuiltReconstructor build_flatnet(const ReconstructorSpec& spec);
BuiltReconstructor build_opencv(const ReconstructorSpec& spec);
// The camera fit for `camera` (its calibration and noise model), or null with the reason in `why`.
std::shared_ptr<const CameraFit> camera_fit_of(const CameraConfig& camera, std::string& why);
// The same for the camera a model was trained with: its file's camera when that names a calibration,
// else the camera file its training config names (data.camera), when it is here with the same geometry.
std::shared_ptr<const CameraFit> model_camera_fit(const ModelFile& model, std::string& why);

}  // namespace flatnet
