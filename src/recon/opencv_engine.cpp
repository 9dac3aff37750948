#include "recon/opencv_engine.hpp"

#include <opencv2/dnn.hpp>

#include "core/error.hpp"

namespace flatnet {

struct OpenCvEngine::Net {
  cv::dnn::Net net;
};

namespace {
// OpenCV's message on one line: where it failed, and the node it could not handle (its later lines).
std::string one_line(const std::string& s) {
  std::string out;
  for (const char c : s) {
    if (c == '\n') {
      if (!out.empty() && out.back() != ' ') out += " ";
    } else {
      out += c;
    }
  }
  while (!out.empty() && out.back() == ' ') out.pop_back();
  return out;
}
}  // namespace

OpenCvEngine::OpenCvEngine(const std::filesystem::path& onnx_file)
    : path_(onnx_file), info_(read_onnx_info(onnx_file)), net_(std::make_unique<Net>()) {
  try {
    net_->net = cv::dnn::readNetFromONNX(onnx_file.string());
  } catch (const cv::Exception& e) {
    throw Error(onnx_file, "OpenCV DNN cannot import this ONNX graph: " + one_line(e.what()));
  }
  if (net_->net.empty()) throw Error(onnx_file, "OpenCV DNN read an empty network");
  net_->net.setPreferableBackend(cv::dnn::DNN_BACKEND_OPENCV);
  net_->net.setPreferableTarget(cv::dnn::DNN_TARGET_CPU);
}

OpenCvEngine::~OpenCvEngine() = default;

CameraConfig OpenCvEngine::camera() const {
  if (info_.camera_yaml.empty())
    throw Error(path_,
                "the ONNX file carries no camera preprocessing (metadata flatnet.camera; not written by "
                "`flatnet export --onnx`?): give " +
                    option_key("recon.camera"));
  return camera_from_yaml_text(info_.camera_yaml, path_);
}

void OpenCvEngine::check_camera(const CameraConfig& camera) const {
  if (camera.raw.crop[2] != info_.rows || camera.raw.crop[3] != info_.cols || camera.scene_size != info_.scene)
    throw Error(path_, "the graph reads " + std::to_string(info_.rows) + "x" + std::to_string(info_.cols) +
                           " planes and makes " + std::to_string(info_.scene) + "x" + std::to_string(info_.scene) +
                           " images; camera '" + camera.name + "' gives other sizes");
  if (info_.level_input != (camera.raw.centring == Centring::level))
    throw Error(path_, std::string("the graph ") + (info_.level_input ? "reads" : "does not read") +
                           " the light level, but camera '" + camera.name + "' has centring '" +
                           centring_name(camera.raw.centring) + "'");
}

torch::Tensor OpenCvEngine::forward(const torch::Tensor& planes) {
  TORCH_CHECK(planes.dim() == 4 && planes.size(1) == 4 && planes.size(2) == info_.rows && planes.size(3) == info_.cols,
              "opencv engine: planes {B,4,", info_.rows, ",", info_.cols, "} expected, got ", planes.sizes());
  std::vector<torch::Tensor> images;
  for (int64_t b = 0; b < planes.size(0); ++b) {
    auto sample = planes[b].unsqueeze(0).to(torch::kFloat32).contiguous();  // {1,4,rows,cols}
    const int dims[4] = {1, 4, static_cast<int>(info_.rows), static_cast<int>(info_.cols)};
    cv::Mat blob(4, dims, CV_32F, sample.data_ptr<float>());
    cv::Mat out;
    try {
      net_->net.setInput(blob, "meas");
      out = net_->net.forward();
    } catch (const cv::Exception& e) {
      throw Error(path_, "OpenCV DNN failed to run the graph: " + one_line(e.what()));
    }
    if (out.dims != 4 || out.size[1] != 3 || out.size[2] != info_.scene || out.size[3] != info_.scene)
      throw Error(path_, "OpenCV DNN gave an output of unexpected shape");
    images.push_back(torch::from_blob(out.ptr<float>(), {3, info_.scene, info_.scene}, torch::kFloat32).clone());
  }
  return torch::stack(images);
}

}  // namespace flatnet
