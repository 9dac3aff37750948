#include "recon/infer.hpp"

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"
#include "recon/run.hpp"

namespace flatnet {

InferReport infer_files(Generator& generator, const CameraConfig& camera,
                        const std::vector<std::filesystem::path>& captures, const InferOptions& opt) {
  check_camera_for_model(generator->options(), camera);
  generator->prepare_inference(opt.levers);
  return infer_files([&](const torch::Tensor& planes) { return generator->forward(planes); }, camera, captures, opt);
}

InferReport infer_files(const BatchForward& forward, const CameraConfig& camera,
                        const std::vector<std::filesystem::path>& captures, const InferOptions& opt) {
  require(!captures.empty(), "--input", "no captures to reconstruct");
  check_output_names(captures, opt.out);
  std::filesystem::create_directories(opt.out);
  c10::InferenceMode no_grad;
  InferReport rep;
  Progress progress("infer", static_cast<int64_t>(captures.size()), opt.progress);
  const auto start = std::chrono::steady_clock::now();
  double model_s = 0;
  for (size_t i = 0; i < captures.size(); i += opt.batch) {
    std::vector<Capture> batch;
    for (size_t j = i; j < std::min(captures.size(), i + opt.batch); ++j)
      batch.push_back(load_capture(captures[j], camera.raw));
    std::vector<torch::Tensor> planes;
    for (const auto& c : batch) planes.push_back(c.planes);
    const auto t0 = std::chrono::steady_clock::now();
    const auto images = forward(torch::stack(planes));  // {B,3,N,N}
    model_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    for (size_t j = 0; j < batch.size(); ++j) {
      auto name = std::filesystem::path(batch[j].name).replace_extension(".png");
      write_rgb8(opt.out / name, images[j]);
    }
    rep.count += static_cast<int64_t>(batch.size());
    progress.tick(static_cast<int64_t>(batch.size()));
  }
  progress.finish();
  const double total = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  rep.model_ms_per_image = 1000.0 * model_s / rep.count;
  rep.images_per_s = rep.count / total;
  return rep;
}

}  // namespace flatnet
