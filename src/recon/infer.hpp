#pragma once
// FlatNet inference on raw captures: raw PNG -> preprocessing of the model's camera -> generator
// -> 256x256 sRGB PNG with the capture's name.
#include <filesystem>
#include <functional>
#include <vector>

#include "core/camera_config.hpp"
#include "nn/generator.hpp"

namespace flatnet {

struct InferOptions {
  std::filesystem::path out;
  int batch = 4;
  bool progress = true;
  InferenceLevers levers;  // exact speed-ups applied to the generator (it is changed in place)
};

struct InferReport {
  int64_t count = 0;
  double model_ms_per_image = 0;  // the network alone
  double images_per_s = 0;        // everything, file I/O included
};

// The camera's crop, scene size and centring must match the generator's (check_camera_for_model).
InferReport infer_files(Generator& generator, const CameraConfig& camera,
                        const std::vector<std::filesystem::path>& captures, const InferOptions& options);

// The batch loop itself, for any engine: {B,4,rows,cols} planes -> {B,3,N,N} images in [0,1]
// (LibTorch's generator above, OpenCV DNN in recon/opencv_engine). `options.levers` is not used.
using BatchForward = std::function<torch::Tensor(const torch::Tensor&)>;
InferReport infer_files(const BatchForward& forward, const CameraConfig& camera,
                        const std::vector<std::filesystem::path>& captures, const InferOptions& options);

}  // namespace flatnet
