#pragma once
// Co-design (issue 27, part 2): the separable mask's code pair learned together with the FlatNet
// that reconstructs its captures. Each training step builds the camera from the codes inside the
// graph (optics/separable_camera: codes -> PhiL, PhiR with sub-pixel sampling, blur, vignetting),
// captures the batch's scenes through it with fresh sensor noise (optics/camera: capture_planes),
// and the generator's loss reaches both the network and the codes.
//   u = tanh(a), v = tanh(b)                     (binary: sign forward, straight-through backward)
//   throughput (1 + mean(u) mean(v)) / 2 held within target +- tolerance by a penalty
//   the camera changes under the first stage (W1^T Y W2): it starts from the starting codes'
//   calibration and follows by learning; the codes freeze at `freeze_at` of the run, so the
//   network's last stretch is trained on the final camera alone.
#include <filesystem>

#include <torch/torch.h>

#include "io/camera_config.hpp"
#include "optics/separable_camera.hpp"

namespace flatnet {

struct CodesignOptions {
  bool learn = false;                // codes.learn: train the codes with the model (else a fixed camera)
  std::filesystem::path init_codes;  // .mat with code_rows, code_cols (the starting camera's, e.g. MLS)
  double lr = 0.005;                 // Adam on the codes' pre-activations
  bool binary = false;               // sign(u), sign(v) forward (for fabrication)
  double target_throughput = 0.5, throughput_tolerance = 0.05;
  double freeze_at = 0.75;        // share of the run (steps, or the time budget) after which the codes stay fixed
  double calib_error = 0.03;      // the written camera's calibration error (relative, as `flatnet mask camera`)
  SeparableCameraOptions camera;  // the sensor and optics the codes sit in (the reference camera's)
  RawGeometry geometry;           // how captures are preprocessed (the run's camera)
};

class CodePairCameraImpl : public torch::nn::Module {
 public:
  explicit CodePairCameraImpl(const CodesignOptions& options);
  std::pair<torch::Tensor, torch::Tensor> codes() const;  // u {K}, v {K} in [-1, 1], with gradients
  torch::Tensor throughput() const;                       // scalar, with gradients
  // 100 * relu(|throughput - target| - tolerance)^2: 0 inside the band (as mask separable's).
  torch::Tensor throughput_penalty() const;
  Rig rig() const;  // the camera of the current codes (with gradients)
  // Linear-light scenes {B,3,N,N} -> preprocessed planes {B,4,h,w} through the current codes, or
  // through `fixed`, a rig() kept while the codes do not change.
  torch::Tensor capture(const torch::Tensor& scene_linear, at::Generator& gen, bool noise = true,
                        const Rig* fixed = nullptr) const;
  const CodesignOptions& options() const { return options_; }

 private:
  CodesignOptions options_;
  torch::Tensor rows_logit_, cols_logit_;  // {K} each: u = tanh(rows_logit)
};
TORCH_MODULE(CodePairCamera);

// The current codes as folder/codes.mat and the camera they make beside it (rig.mat, calib.mat
// with options.calib_error, camera.yaml with `geometry`'s preprocessing), as `flatnet mask camera`
// writes them (write_code_pair_camera). Every file atomically.
void write_code_camera(const std::filesystem::path& folder, const CodePairCamera& camera, const CameraConfig& geometry);

}  // namespace flatnet
