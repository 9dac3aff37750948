#include "optics/simulator.hpp"

#include <atomic>
#include <mutex>
#include <random>
#include <thread>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"

namespace flatnet {

torch::Tensor display_scene(const std::filesystem::path& image, int64_t size) {
  auto rgb = resize(read_rgb(image), size, size);
  return torch::round(rgb.clamp(0, 1) * 255.0f) / 255.0f;  // what an 8-bit display shows
}

std::pair<std::vector<std::string>, std::vector<std::string>> split_train_val(const std::vector<std::string>& names,
                                                                           double val_fraction, uint64_t seed) {
  std::vector<std::string> shuffled = names;
  std::mt19937_64 rng(seed);
  std::shuffle(shuffled.begin(), shuffled.end(), rng);
  const auto n_val = static_cast<size_t>(std::llround(val_fraction * shuffled.size()));
  std::vector<std::string> val(shuffled.begin(), shuffled.begin() + n_val), train(shuffled.begin() + n_val, shuffled.end());
  std::sort(val.begin(), val.end());
  std::sort(train.begin(), train.end());
  return {train, val};
}

std::pair<std::vector<std::filesystem::path>, std::vector<std::filesystem::path>> split_image_files(
    const std::filesystem::path& dir, double val_fraction, uint64_t seed) {
  const auto images = list_images(dir, kImageExtensions);
  require(!images.empty(), dir, "no readable images (png, jpg, tif, bmp) in this folder");
  std::vector<std::string> names;
  std::map<std::string, std::filesystem::path> by_name;
  for (const auto& p : images) names.push_back(p.filename().string()), by_name[p.filename().string()] = p;
  auto [train, val] = split_train_val(names, val_fraction, seed);
  std::vector<std::filesystem::path> a, b;
  for (const auto& n : train) a.push_back(by_name.at(n));
  for (const auto& n : val) b.push_back(by_name.at(n));
  return {a, b};
}

namespace {

void write_lists(const std::filesystem::path& out, const std::string& split, const std::vector<std::string>& names) {
  std::string meas, gt;
  for (const auto& n : names) {
    meas += "meas/" + n + "\n";
    gt += "gt/" + n + "\n";
  }
  write_text_atomically(out / (split + "_meas.txt"), meas);
  write_text_atomically(out / (split + "_gt.txt"), gt);
}

}  // namespace

std::pair<int64_t, int64_t> write_dataset_lists(const std::filesystem::path& out, const std::vector<std::string>& names,
                                                const std::vector<std::string>& complete, double val_fraction, uint64_t seed) {
  auto [train, val] = split_train_val(names, val_fraction, seed);
  auto done = complete;
  std::sort(done.begin(), done.end());
  auto keep_done = [&](std::vector<std::string>& v) {
    v.erase(std::remove_if(v.begin(), v.end(), [&](const std::string& n) { return !std::binary_search(done.begin(), done.end(), n); }),
            v.end());
  };
  keep_done(train);
  keep_done(val);
  write_lists(out, "train", train);
  write_lists(out, "val", val);
  return {static_cast<int64_t>(train.size()), static_cast<int64_t>(val.size())};
}

SimulateReport simulate_dataset(const Rig& rig, const SimulateOptions& opt) {
  require(opt.val_fraction >= 0 && opt.val_fraction <= 1, "--val-fraction", "must be within [0, 1]");
  require(opt.size == rig.scene_size(), "--size",
          "the rig's matrices take " + std::to_string(rig.scene_size()) + "x" + std::to_string(rig.scene_size()) +
              " scenes, got " + std::to_string(opt.size));
  auto images = list_images(opt.images, kImageExtensions);
  if (opt.limit > 0 && static_cast<int64_t>(images.size()) > opt.limit) images.resize(opt.limit);
  require(!images.empty(), opt.images, "no images (.png .jpg .jpeg .tif .bmp) in this folder");
  std::vector<std::string> names;
  for (const auto& p : images) names.push_back(p.stem().string() + ".png");
  for (size_t i = 1; i < names.size(); ++i)
    require(names[i] != names[i - 1], images[i], "two images share the name " + names[i]);

  std::filesystem::create_directories(opt.out / "meas");
  std::filesystem::create_directories(opt.out / "gt");
  SimulateReport report;
  report.total = static_cast<int64_t>(images.size());

  const int workers = opt.workers > 0 ? opt.workers : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  std::atomic<size_t> next{0};
  std::atomic<int64_t> simulated{0}, skipped{0};
  std::mutex error_mutex;
  std::string first_error;
  Progress progress("simulate", report.total, opt.progress);
  const auto start = std::chrono::steady_clock::now();
  auto work = [&]() {
    c10::InferenceMode guard;
    for (size_t i = next++; i < images.size(); i = next++) {
      {
        std::lock_guard<std::mutex> lock(error_mutex);
        if (!first_error.empty()) return;
      }
      const auto meas_path = opt.out / "meas" / names[i], gt_path = opt.out / "gt" / names[i];
      try {
        if (std::filesystem::exists(meas_path) && std::filesystem::exists(gt_path)) {
          ++skipped;
        } else {
          auto scene = display_scene(images[i], opt.size);
          // Per-image generator: the noise does not depend on thread scheduling.
          auto gen = at::detail::createCPUGenerator(stable_hash(names[i], opt.seed));
          auto raw = simulate_raw(rig, scene, opt.noise, gen);
          write_rgb8(gt_path, scene);
          write_gray16(meas_path, raw);
          ++simulated;
        }
      } catch (const std::exception& e) {
        std::lock_guard<std::mutex> lock(error_mutex);
        if (first_error.empty()) first_error = e.what();
        return;
      }
      progress.tick();
    }
  };
  std::vector<std::thread> pool;
  for (int t = 0; t < workers; ++t) pool.emplace_back(work);
  for (auto& t : pool) t.join();
  progress.finish();
  if (!first_error.empty()) throw Error(first_error);
  report.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  report.simulated = simulated;
  report.skipped = skipped;

  std::tie(report.train, report.val) = write_dataset_lists(opt.out, names, names, opt.val_fraction, opt.seed);
  return report;
}

}  // namespace flatnet
