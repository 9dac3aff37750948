#pragma once
// Display-capture dataset simulation: photographs -> (capture, scene) pairs in FlatNet's layout.
#include <filesystem>
#include <vector>

#include "optics/camera.hpp"

namespace flatnet {

struct SimulateOptions {
  std::filesystem::path images;   // folder of photographs
  std::filesystem::path out;      // dataset folder: meas/, gt/, train_*.txt, val_*.txt
  double val_fraction = 0.1;      // share of images listed in val_*.txt
  uint64_t seed = 0;              // split and noise are deterministic for a seed
  bool noise = true;
  int64_t size = 256;             // scene side (the display image is resized, aspect ignored)
  int workers = 0;                // <= 0: all cores
  bool progress = true;
  int64_t limit = 0;              // > 0: only the first `limit` images (sorted by name)
};

struct SimulateReport {
  int64_t total = 0, simulated = 0, skipped = 0, train = 0, val = 0;
  double seconds = 0;  // wall time of the simulation loop
};

// Simulates every image not yet done (resumable: finished pairs are skipped; files appear
// atomically), then writes the lists. Errors name the first unreadable image.
SimulateReport simulate_dataset(const Rig& rig, const SimulateOptions& options);

// The deterministic train/validation split `simulate_dataset` writes (and on-the-fly simulation
// uses): shuffle with the seed, the first round(fraction * n) are validation; both sorted.
std::pair<std::vector<std::string>, std::vector<std::string>> split_train_val(const std::vector<std::string>& names,
                                                                           double val_fraction, uint64_t seed);
// Writes train_meas/gt.txt and val_meas/gt.txt: the split_train_val split of all `names`, listing
// only the `complete` ones (a partially collected dataset is trainable, and its split is stable).
// Returns {train, val} counts listed.
std::pair<int64_t, int64_t> write_dataset_lists(const std::filesystem::path& out, const std::vector<std::string>& names,
                                                const std::vector<std::string>& complete, double val_fraction, uint64_t seed);
// The photographs of a folder (any image extension), split by split_train_val's rule:
// {train, held-out}. Errors when the folder has no readable images.
std::pair<std::vector<std::filesystem::path>, std::vector<std::filesystem::path>> split_image_files(
    const std::filesystem::path& dir, double val_fraction, uint64_t seed);
// The scene a display shows for a photograph: resized to size x size, quantised to 8 bits.
torch::Tensor display_scene(const std::filesystem::path& image, int64_t size);

}  // namespace flatnet
