#pragma once
// A second, LibTorch-free inference path for deployment: an ONNX file from `flatnet export --onnx`
// run through OpenCV's DNN module (`flatnet infer --engine opencv`).
#include <filesystem>
#include <memory>

#include <torch/torch.h>

#include "io/camera_config.hpp"
#include "nn/onnx_export.hpp"

namespace flatnet {

class OpenCvEngine {
 public:
  // Reads the network; errors name the file (not ONNX, or a graph OpenCV cannot import).
  explicit OpenCvEngine(const std::filesystem::path& onnx_file);
  ~OpenCvEngine();
  // {B,4,rows,cols} planes -> {B,3,N,N} images in [0,1] (the graph is batch 1: one run per sample).
  torch::Tensor forward(const torch::Tensor& planes);
  const OnnxModelInfo& info() const { return info_; }
  // The camera the file carries (its metadata), for the preprocessing of raw captures.
  CameraConfig camera() const;
  // Throws unless `camera` preprocesses captures the way the graph expects (sizes, light level).
  void check_camera(const CameraConfig& camera) const;

 private:
  std::filesystem::path path_;
  OnnxModelInfo info_;
  struct Net;  // cv::dnn::Net, kept out of this header
  std::unique_ptr<Net> net_;
};

}  // namespace flatnet
