#pragma once
// Training data for the reconstruction networks: (measurement planes, ground truth) pairs from a
// FlatNet-layout dataset on disk, or simulated on the fly from photographs through a rig (fresh
// noise every epoch), and a loader that builds batches in background threads. The batch for a
// step depends only on (seed, step): runs resumed from a checkpoint see the same data.
#include <condition_variable>
#include <filesystem>
#include <iterator>
#include <map>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include <torch/torch.h>

#include "io/camera_config.hpp"
#include "io/dataset.hpp"
#include "optics/camera.hpp"
#include "optics/simulator.hpp"

namespace flatnet {

struct Sample {
  torch::Tensor meas;  // {4,rows,cols} preprocessed measurement planes
  torch::Tensor gt;    // {3,N,N} sRGB in [0,1]
  std::string name;
  torch::Tensor scene{};  // {3,N,N} linear light, only from sources that leave the capture to the trainer (co-design)
  int condition = 0;      // the light it was validated under: an index into kJudgedConditions (0: display)
};

// The three conditions the evaluation sets judge a model under (scripts/make_eval_sets.sh):
// display captures, dim scenes at a third of the display's light, and scenes with one small lamp
// 20x display white. data.val_light "judged" validates under all three in turn.
inline constexpr const char* kJudgedConditions[] = {"display", "dim", "lamp"};
inline constexpr int64_t kJudgedConditionCount = std::size(kJudgedConditions);
inline constexpr double kJudgedDimExposure = 0.33, kJudgedLampGain = 20;
// The light of a judged condition (an index into kJudgedConditions; the lamp placed by `gen`).
SceneLight judged_light(int condition, int64_t scene_size, at::Generator& gen);

// data.val_light: the validation's light.
enum class ValidationLight { display, judged };
ValidationLight parse_validation_light(const std::string& s, const std::string& key);

class PairSource {
 public:
  virtual ~PairSource() = default;
  virtual int64_t size() const = 0;
  // Item i; `epoch` varies the simulated noise (disk sources ignore it).
  virtual Sample load(int64_t i, int64_t epoch) const = 0;
};

// Pairs listed in a FlatNet-layout dataset.
class DiskPairs : public PairSource {
 public:
  DiskPairs(std::vector<Pair> pairs, CameraConfig camera);
  int64_t size() const override { return static_cast<int64_t>(pairs_.size()); }
  Sample load(int64_t i, int64_t epoch) const override;

 private:
  std::vector<Pair> pairs_;
  CameraConfig camera_;
};

// Photographs shown on a (simulated) display and captured through the rig, noise drawn from a
// generator seeded by (seed, image, epoch). With a LightAugment, each sample's scene light is
// redrawn from the same generator (dim scenes, lamps; see optics/simulator.hpp) and the ground
// truth is what that scene shows. With `judged`, item i is lit as judged_light(i) instead (the
// validation set of data.val_light "judged"). Display scenes are decoded once and kept (8-bit, 192 KiB each).
// Without a rig, samples carry the linear scene instead of a capture (the co-design trainer
// captures it through the camera it is learning).
class SimulatedPairs : public PairSource {
 public:
  SimulatedPairs(std::vector<std::filesystem::path> images, std::shared_ptr<const Rig> rig, CameraConfig camera,
                 uint64_t seed, LightAugment light = {}, bool judged = false);
  int64_t size() const override { return static_cast<int64_t>(images_.size()); }
  Sample load(int64_t i, int64_t epoch) const override;

 private:
  torch::Tensor scene(int64_t i) const;  // {3,N,N} display sRGB, cached
  std::vector<std::filesystem::path> images_;
  std::shared_ptr<const Rig> rig_;
  CameraConfig camera_;
  uint64_t seed_;
  LightAugment light_;
  bool judged_ = false;
  mutable std::mutex cache_mutex_;
  mutable std::vector<torch::Tensor> cache_;  // uint8 {3,N,N}
};

struct Batch {
  torch::Tensor meas;  // {B,4,rows,cols}
  torch::Tensor gt;    // {B,3,N,N}
  int64_t step = 0;
  torch::Tensor scene{};  // {B,3,N,N} linear light, when the source gives scenes (then meas is undefined)
};

struct LoaderOptions {
  int64_t batch = 4;
  uint64_t seed = 0;
  int64_t first_step = 0;        // resume: the step whose batch comes first
  int workers = 1;               // background threads
  int prefetch = 4;              // batches built ahead at most
  double noise_augment = 0.0;    // std of Gaussian noise added to the planes (FlatNet: 0.003)
  int world_size = 1, rank = 0;  // data-parallel: rank r takes slice r of each step's global batch
};

// Endless stream of shuffled batches. Sample k = (step * world + rank) * batch + j is item perm_e[k mod n] of epoch
// e = k / n, with perm_e a permutation drawn from (seed, e).
class BatchLoader {
 public:
  BatchLoader(std::shared_ptr<const PairSource> source, LoaderOptions options);
  ~BatchLoader();
  BatchLoader(const BatchLoader&) = delete;
  BatchLoader& operator=(const BatchLoader&) = delete;
  Batch next();
  // Seconds the consumer has spent waiting for data (0 when loading keeps up).
  double wait_seconds() const { return wait_s_; }

 private:
  Batch build(int64_t step) const;
  void work();

  std::shared_ptr<const PairSource> source_;
  LoaderOptions opt_;
  std::mutex mutex_;
  std::condition_variable cv_;
  int64_t next_to_build_, next_to_take_;
  std::map<int64_t, Batch> ready_;
  std::map<int64_t, std::exception_ptr> failed_;
  bool stop_ = false;
  double wait_s_ = 0;
  std::vector<std::thread> threads_;
};

// Index permutation of 0..n-1 for (seed, epoch).
std::vector<int64_t> epoch_permutation(int64_t n, uint64_t seed, int64_t epoch);

// Loads items [0, count) of a source at epoch 0 (validation sets), count <= 0 meaning all.
std::vector<Sample> load_all(const PairSource& source, int64_t count, int workers);

}  // namespace flatnet
