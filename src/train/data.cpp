#include "train/data.hpp"

#include <random>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/image.hpp"
#include "io/raw.hpp"
#include "optics/simulator.hpp"

namespace flatnet {

DiskPairs::DiskPairs(std::vector<Pair> pairs, CameraConfig camera)
    : pairs_(std::move(pairs)), camera_(std::move(camera)) {
  if (pairs_.empty()) throw Error("dataset: no pairs to train on");
}

Sample DiskPairs::load(int64_t i, int64_t) const {
  const auto& p = pairs_.at(i);
  Sample s;
  s.meas = load_capture(p.meas, camera_.raw).planes;
  auto gt = read_rgb(p.gt);
  if (gt.size(1) != camera_.scene_size || gt.size(2) != camera_.scene_size)
    gt = resize(gt, camera_.scene_size, camera_.scene_size).clamp(0, 1);
  s.gt = gt;
  s.name = p.meas.filename().string();
  return s;
}

SimulatedPairs::SimulatedPairs(std::vector<std::filesystem::path> images, std::shared_ptr<const Rig> rig,
                               CameraConfig camera, uint64_t seed, LightAugment light, bool judged)
    : images_(std::move(images)),
      rig_(std::move(rig)),
      camera_(std::move(camera)),
      seed_(seed),
      light_(light),
      judged_(judged),
      cache_(images_.size()) {
  if (images_.empty()) throw Error("data.images: no images to simulate from");
}

torch::Tensor SimulatedPairs::scene(int64_t i) const {
  {
    std::lock_guard<std::mutex> lock(cache_mutex_);
    if (cache_.at(i).defined()) return cache_[i].to(torch::kFloat32) / 255.0f;
  }
  const auto display = display_scene(images_[i], camera_.scene_size);  // exact multiples of 1/255
  std::lock_guard<std::mutex> lock(cache_mutex_);
  cache_[i] = torch::round(display * 255.0f).to(torch::kUInt8);
  return display;
}

Sample SimulatedPairs::load(int64_t i, int64_t epoch) const {
  const auto& image = images_.at(i);
  Sample s;
  s.gt = scene(i);  // {3,N,N}
  auto gen =
      at::detail::createCPUGenerator(stable_hash(image.filename().string() + "#" + std::to_string(epoch), seed_));
  s.name = image.filename().string();
  const double gamma = camera_.display_gamma;
  torch::Tensor linear = display_to_light(s.gt, gamma);
  if (judged_) {
    s.condition = static_cast<int>(i % kJudgedConditionCount);
    if (s.condition != 0) {  // display captures keep the display image as truth, as the held-out set does
      linear = lit_scene(s.gt, judged_light(s.condition, camera_.scene_size, gen), gamma);
      s.gt = visible_scene(linear, gamma);
    }
  } else if (light_.active()) {
    linear = lit_scene(s.gt, draw_scene_light(light_, camera_.scene_size, gen), gamma);
    s.gt = visible_scene(linear, gamma);
  }
  if (!rig_) {
    s.scene = linear;
    return s;
  }
  const auto raw = simulate_raw_linear(*rig_, linear, true, gen);  // stored 16-bit codes
  s.meas = preprocess_raw(raw.to(torch::kFloat32) / 65535.0f, camera_.raw);
  return s;
}

SceneLight judged_light(int condition, int64_t scene_size, at::Generator& gen) {
  SceneLight light;
  switch (condition) {
    case 1:
      light.exposure = kJudgedDimExposure;
      break;
    case 2:
      place_lamp(light, scene_size, gen);
      light.lamp_gain = kJudgedLampGain;
      break;
    default:
      break;
  }
  return light;
}

ValidationLight parse_validation_light(const std::string& s, const std::string& key) {
  if (s == "display") return ValidationLight::display;
  if (s == "judged") return ValidationLight::judged;
  throw Error("config: " + key + " must be display or judged, got '" + s + "'");
}

std::vector<int64_t> epoch_permutation(int64_t n, uint64_t seed, int64_t epoch) {
  std::vector<int64_t> perm(n);
  std::iota(perm.begin(), perm.end(), 0);
  std::mt19937_64 rng(seed * 1000003ULL + static_cast<uint64_t>(epoch));
  std::shuffle(perm.begin(), perm.end(), rng);
  return perm;
}

BatchLoader::BatchLoader(std::shared_ptr<const PairSource> source, LoaderOptions options)
    : source_(std::move(source)), opt_(options), next_to_build_(options.first_step), next_to_take_(options.first_step) {
  require(source_->size() > 0, "dataset", "empty");
  for (int t = 0; t < std::max(1, opt_.workers); ++t)
    threads_.emplace_back([this] {
      single_threaded_worker();
      work();
    });
}

BatchLoader::~BatchLoader() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  for (auto& t : threads_) t.join();
}

Batch BatchLoader::build(int64_t step) const {
  const int64_t n = source_->size();
  std::vector<torch::Tensor> meas, gt, scenes;
  int64_t cached_epoch = -1;
  std::vector<int64_t> perm;
  for (int64_t j = 0; j < opt_.batch; ++j) {
    // Global sample index: step s's global batch is world * batch consecutive samples.
    const int64_t k = (step * opt_.world_size + opt_.rank) * opt_.batch + j, epoch = k / n;
    if (epoch != cached_epoch) perm = epoch_permutation(n, opt_.seed, epoch), cached_epoch = epoch;
    auto s = source_->load(perm[k % n], epoch);
    if (s.scene.defined()) {  // the trainer captures it (and adds noise_augment)
      scenes.push_back(s.scene);
    } else {
      if (opt_.noise_augment > 0) {
        auto gen = at::detail::createCPUGenerator(opt_.seed * 7919ULL + static_cast<uint64_t>(k));
        s.meas = s.meas + opt_.noise_augment * at::randn(s.meas.sizes(), gen);
      }
      meas.push_back(s.meas);
    }
    gt.push_back(s.gt);
  }
  Batch b{{}, torch::stack(gt), step};
  if (!meas.empty()) b.meas = torch::stack(meas);
  if (!scenes.empty()) b.scene = torch::stack(scenes);
  return b;
}

void BatchLoader::work() {
  while (true) {
    int64_t step;
    {
      std::unique_lock<std::mutex> lock(mutex_);
      cv_.wait(lock, [&] { return stop_ || next_to_build_ < next_to_take_ + opt_.prefetch; });
      if (stop_) return;
      step = next_to_build_++;
    }
    try {
      auto b = build(step);
      std::lock_guard<std::mutex> lock(mutex_);
      ready_[step] = std::move(b);
    } catch (...) {
      std::lock_guard<std::mutex> lock(mutex_);
      failed_[step] = std::current_exception();
    }
    cv_.notify_all();
  }
}

Batch BatchLoader::next() {
  const auto t0 = std::chrono::steady_clock::now();
  std::unique_lock<std::mutex> lock(mutex_);
  const int64_t step = next_to_take_;
  cv_.wait(lock, [&] { return ready_.count(step) || failed_.count(step); });
  wait_s_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (failed_.count(step)) std::rethrow_exception(failed_.at(step));
  Batch b = std::move(ready_.at(step));
  ready_.erase(step);
  ++next_to_take_;
  lock.unlock();
  cv_.notify_all();
  return b;
}

std::vector<Sample> load_all(const PairSource& source, int64_t count, int workers) {
  const int64_t n = count <= 0 ? source.size() : std::min(count, source.size());
  std::vector<Sample> out(n);
  parallel_for_index(n, workers, [&](int64_t i) { out[i] = source.load(i, 0); });
  return out;
}

}  // namespace flatnet
