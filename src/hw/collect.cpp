#include "hw/collect.hpp"

#include "core/error.hpp"
#include "core/util.hpp"
#include "hw/capture.hpp"
#include "io/image.hpp"
#include "optics/simulator.hpp"

namespace flatnet {

CollectReport collect(const std::vector<CollectItem>& items, FrameSource& source, Display& display,
                      const CollectOptions& opt,
                      const std::function<std::filesystem::path(const std::string&)>& meas_path,
                      const std::function<void(const std::string&, const torch::Tensor&)>& before_write) {
  CollectReport rep;
  rep.total = static_cast<int64_t>(items.size());
  std::vector<const CollectItem*> todo;
  for (const auto& item : items) {
    if (std::filesystem::exists(meas_path(item.name)))
      ++rep.skipped;
    else
      todo.push_back(&item);
  }
  const int64_t planned = opt.limit > 0 ? std::min<int64_t>(opt.limit, todo.size()) : static_cast<int64_t>(todo.size());
  Progress progress("collect", planned, opt.progress);
  const auto start = std::chrono::steady_clock::now();
  const FinishItemOnInterrupt finish_frame;  // Ctrl-C ends this frame, then the loop
  for (int64_t i = 0; i < planned; ++i) {
    if (interrupted()) break;
    const auto& item = *todo[i];
    const auto scene = item.scene();
    display.show(scene);
    if (display.wait(std::max(1, opt.settle_ms))) break;  // Esc / q
    // Only frames that arrive after the settle time can show this scene.
    std::vector<uint64_t> ids;
    const auto mean = average_frames(source, opt.average, FrameSource::Clock::now(), &ids);
    if (before_write) before_write(item.name, scene);
    auto sidecar = capture_sidecar(source, opt.average, ids);
    sidecar["scene"] = item.name;
    sidecar["settle_ms"] = opt.settle_ms;
    write_raw_capture(meas_path(item.name), mean, source.format(), sidecar);
    ++rep.captured;
    progress.tick();
  }
  progress.finish();
  rep.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  rep.stopped = rep.skipped + rep.captured < rep.total;
  return rep;
}

CollectReport collect_dataset(const std::vector<std::filesystem::path>& images, FrameSource& source, Display& display,
                              const DatasetCollectOptions& opt) {
  require_option(!images.empty(), "collect.images", "no photographs to show");
  std::vector<CollectItem> items;
  std::vector<std::string> names;
  for (const auto& image : images) {
    const auto name = image.stem().string() + ".png";
    require(names.empty() || std::find(names.begin(), names.end(), name) == names.end(), image,
            "two images share the name " + name);
    names.push_back(name);
    items.push_back({name, [image, size = opt.scene_size] { return display_scene(image, size); }});
  }
  std::filesystem::create_directories(opt.out / "meas");
  std::filesystem::create_directories(opt.out / "gt");
  auto meas = [&](const std::string& name) { return opt.out / "meas" / name; };
  // The ground truth is exactly what was shown (8-bit, scene_size square).
  auto write_gt = [&](const std::string& name, const torch::Tensor& scene) {
    write_rgb8(opt.out / "gt" / name, scene);
  };
  const auto rep = collect(items, source, display, opt.collect, meas, write_gt);

  std::vector<std::string> complete;
  for (const auto& n : names)
    if (std::filesystem::exists(meas(n)) && std::filesystem::exists(opt.out / "gt" / n)) complete.push_back(n);
  write_dataset_lists(opt.out, names, complete, opt.val_fraction, opt.seed);
  return rep;
}

}  // namespace flatnet
