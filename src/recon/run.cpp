#include "recon/run.hpp"

#include <fnmatch.h>

#include <map>
#include <set>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"
#include "recon/tikhonov.hpp"

namespace flatnet {

std::vector<std::filesystem::path> collect_captures(const std::filesystem::path& input) {
  const auto pattern = input.filename().string();
  if (pattern.find_first_of("*?[") != std::string::npos) {  // DIR/fc_*.png: matching files, sorted
    const auto dir = input.parent_path().empty() ? std::filesystem::path(".") : input.parent_path();
    require(std::filesystem::is_directory(dir), dir, "no such folder");
    std::vector<std::filesystem::path> files;
    for (const auto& e : std::filesystem::directory_iterator(dir))
      if (e.is_regular_file() && ::fnmatch(pattern.c_str(), e.path().filename().c_str(), 0) == 0)
        files.push_back(e.path());
    std::sort(files.begin(), files.end());
    require(!files.empty(), input, "no file matches this pattern");
    return files;
  }
  require(std::filesystem::exists(input), input, "no such file or folder");
  if (std::filesystem::is_directory(input)) {
    auto files = list_images(input, {".png"});
    require(!files.empty(), input, "no .png captures in this folder");
    return files;
  }
  if (input.extension() == ".txt") {  // a list (e.g. a dataset's val_meas.txt), relative to its folder
    std::vector<std::filesystem::path> files;
    for (const auto& line : read_lines(input)) {
      const auto p = input.parent_path() / line;
      require(std::filesystem::exists(p), input, "lists '" + line + "', which does not exist");
      files.push_back(p);
    }
    require(!files.empty(), input, "an empty list");
    return files;
  }
  return {input};
}

void check_output_names(const std::vector<std::filesystem::path>& captures, const std::filesystem::path& out) {
  auto canonical = [](const std::filesystem::path& p) {
    std::error_code ec;
    auto c = std::filesystem::weakly_canonical(p, ec);
    return ec ? std::filesystem::absolute(p).lexically_normal() : c;
  };
  std::set<std::filesystem::path> inputs;
  for (const auto& c : captures) inputs.insert(canonical(c));
  std::map<std::filesystem::path, std::filesystem::path> writer_of;  // output -> the capture that makes it
  for (const auto& c : captures) {
    const auto target = canonical(out / std::filesystem::path(c.filename()).replace_extension(".png"));
    const auto [it, fresh] = writer_of.emplace(target, c);
    if (!fresh)
      throw Error(c, "has the same name as " + it->second.string() + ": both would be written to " + target.string() +
                         " (reconstruct them into separate --out folders)");
    if (inputs.count(target))
      throw Error("--out",
                  "writing " + target.string() + " would overwrite a capture being read; choose another --out folder");
  }
}

torch::Tensor planes_to_srgb(const torch::Tensor& planes) {
  return linear_to_srgb(bayer_planes_to_rgb(planes).clamp(0, 1));
}

ReconReport reconstruct_files(const CameraConfig& camera, const Calibration& calib,
                              const std::vector<std::filesystem::path>& captures, const ReconOptions& opt) {
  require(opt.method == "tikhonov" || opt.method == "tv", "--method",
          "must be tikhonov or tv, got '" + opt.method + "'");
  check_output_names(captures, opt.out);
  c10::InferenceMode guard;
  std::function<torch::Tensor(const torch::Tensor&)> solve;
  if (opt.method == "tikhonov") {
    auto tik = std::make_shared<Tikhonov>(calib, opt.lambda > 0 ? opt.lambda : camera.tikhonov_lambda);
    solve = [tik](const torch::Tensor& y) { return (*tik)(y); };
  } else {
    TVOptions tv;
    tv.lambda = opt.lambda > 0 ? opt.lambda : camera.tv_lambda;
    tv.tikhonov_lambda = camera.tikhonov_lambda;
    auto solver = std::make_shared<TVSolver>(calib, tv);
    solve = [solver](const torch::Tensor& y) { return (*solver)(y); };
  }
  ReconReport report;
  Progress progress(opt.method, static_cast<int64_t>(captures.size()), opt.progress);
  double recon_s = 0;
  const auto start = std::chrono::steady_clock::now();
  for (size_t first = 0; first < captures.size(); first += opt.batch) {
    const size_t last = std::min(captures.size(), first + static_cast<size_t>(opt.batch));
    std::vector<torch::Tensor> planes;
    for (size_t i = first; i < last; ++i) planes.push_back(load_centred_planes(captures[i], camera.raw));
    auto Y = torch::stack(planes);  // {B,4,h,w}
    const auto t0 = std::chrono::steady_clock::now();
    auto X = solve(Y);  // {B,4,N,N}
    recon_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    for (size_t i = first; i < last; ++i) {
      auto name = captures[i].filename();
      name.replace_extension(".png");
      write_rgb8(opt.out / name, planes_to_srgb(X[i - first]));
      progress.tick();
    }
  }
  progress.finish();
  report.count = static_cast<int64_t>(captures.size());
  report.recon_ms_per_capture = 1000.0 * recon_s / std::max<int64_t>(1, report.count);
  report.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return report;
}

}  // namespace flatnet
