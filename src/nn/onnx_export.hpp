#pragma once
// A trained generator as an ONNX graph, for deployment without LibTorch (OpenCV DNN, ONNX Runtime).
//
// The graph is written node by node with Debian's libonnx protobuf classes (not traced), in a form
// OpenCV 4.6's importer reads: no Identity nodes, constants on the right of MatMul, eval-mode batch
// norm folded into the convolutions before it, opset 13.
//   input  `meas`  float32 {batch,4,rows,cols} (the batch axis is symbolic): the planes (b, gb, gr, r) exactly as the
//   model's camera
//                  preprocessing makes them (load_capture; with centring "level" the plane means
//                  are part of the input and the graph splits them off as the generator does);
//   output `image` float32 {batch,3,N,N} in [0,1] (sRGB, as `flatnet infer` writes it).
// The model's camera preprocessing travels in the metadata ("flatnet.camera", YAML), so a deployed
// engine reads the same raw frames the same way (`flatnet infer --engine opencv`).
#include <filesystem>
#include <string>

#include "io/camera_config.hpp"
#include "nn/generator.hpp"

namespace flatnet {

struct OnnxExportReport {
  int64_t nodes = 0;
  int64_t initializers = 0;  // constant tensors (weights)
  int64_t bytes = 0;         // size of the file written
};

// Builds the graph of `generator` (inversion or Tikhonov first stage; U-Net or DnCNN enhancer),
// checks it with ONNX's checker and strict shape inference, and writes it atomically.
// Errors name the file, or the part of the model that ONNX export does not cover (RCAN).
OnnxExportReport export_onnx(const std::filesystem::path& path, Generator& generator, const CameraConfig& camera);

// The metadata an exported file carries: the camera preprocessing text ("flatnet.camera") and the
// input/output sizes. Errors name the file when it is not an ONNX model written by flatnet.
struct OnnxModelInfo {
  std::string camera_yaml;
  int64_t rows = 0, cols = 0, scene = 0;
  bool level_input = false;  // the graph reads the light level (the camera's centring must be "level")
};
OnnxModelInfo read_onnx_info(const std::filesystem::path& path);

}  // namespace flatnet
