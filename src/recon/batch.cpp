#include "recon/batch.hpp"

#include <fnmatch.h>

#include <map>
#include <set>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"

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
                         " (reconstruct them into separate recon.out folders)");
    if (inputs.count(target))
      throw Error("recon.out", "writing " + target.string() +
                                 " would overwrite a capture being read; choose another recon.out folder");
  }
}

BatchReport reconstruct_files(Reconstructor& engine, const CameraConfig& camera,
                              const std::vector<std::filesystem::path>& captures, const BatchOptions& opt) {
  require(!captures.empty(), "recon.input", "no captures to reconstruct");
  require(opt.batch >= 1, "recon.batch", "must be at least 1");
  check_output_names(captures, opt.out);
  std::filesystem::create_directories(opt.out);
  c10::InferenceMode no_grad;
  BatchReport report;
  Progress progress(opt.label, static_cast<int64_t>(captures.size()), opt.progress);
  const auto start = std::chrono::steady_clock::now();
  double engine_s = 0;
  for (size_t first = 0; first < captures.size(); first += opt.batch) {
    const size_t last = std::min(captures.size(), first + static_cast<size_t>(opt.batch));
    std::vector<torch::Tensor> planes;
    for (size_t i = first; i < last; ++i) planes.push_back(load_capture(captures[i], camera.raw).planes);
    const auto t0 = std::chrono::steady_clock::now();
    const auto images = engine.reconstruct(torch::stack(planes));  // {B,4,rows,cols} -> {B,3,N,N}
    engine_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    for (size_t i = first; i < last; ++i) {
      auto name = captures[i].filename();
      write_rgb8(opt.out / name.replace_extension(".png"), images[static_cast<int64_t>(i - first)]);
    }
    report.count += static_cast<int64_t>(last - first);
    progress.tick(static_cast<int64_t>(last - first));
  }
  progress.finish();
  report.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  report.ms_per_capture = 1000.0 * engine_s / report.count;
  report.captures_per_s = report.count / std::max(1e-9, report.seconds);
  return report;
}

}  // namespace flatnet
