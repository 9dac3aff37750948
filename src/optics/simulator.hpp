#pragma once
// Display-capture dataset simulation: photographs -> (capture, scene) pairs in FlatNet's layout.
#include <filesystem>
#include <vector>

#include "optics/camera.hpp"

namespace flatnet {

// Real scenes are not display captures: their light ranges from dim rooms to lamps far brighter
// than a display's white. A SceneLight turns a display image into such a scene, in linear light
// (1 = display white), where the camera integrates it (camera README, "The true response").
struct SceneLight {
  double exposure = 1.0;                               // scene radiance relative to the display's
  bool lamp = false;                                   // a small bright disk added to the scene
  double lamp_gain = 20;                               // its radiance relative to display white
  double lamp_row = 0, lamp_col = 0, lamp_radius = 2;  // centre and radius in scene pixels
};
// exposure * display_to_light(display, display_gamma) + lamp: {3,N,N} linear light
// (display_gamma: CameraConfig's, 0 for the sRGB curve).
torch::Tensor lit_scene(const torch::Tensor& display_srgb, const SceneLight& light, double display_gamma);
// What a reconstruction should show of a linear scene: the display value of the scene clipped to
// display white, through the same curve.
torch::Tensor visible_scene(const torch::Tensor& linear, double display_gamma);

// Random scene light for training (data.light.* in the config).
struct LightAugment {
  double exposure_probability = 0;                // share of samples whose light is redrawn
  double exposure_min = 0.2, exposure_max = 1.5;  // drawn log-uniformly
  double lamp_probability = 0;                    // share of samples with a lamp
  double lamp_min = 5, lamp_max = 50;             // lamp gain, log-uniform
  bool active() const { return exposure_probability > 0 || lamp_probability > 0; }
};
SceneLight draw_scene_light(const LightAugment& augment, int64_t scene_size, at::Generator& gen);
// A lamp at a random place (used by `flatnet simulate --lamp`): radius 1.5..4 px, kept 8 px from the edges.
void place_lamp(SceneLight& light, int64_t scene_size, at::Generator& gen);

struct SimulateOptions {
  std::filesystem::path images;  // folder of photographs
  std::filesystem::path out;     // dataset folder: meas/, gt/, train_*.txt, val_*.txt
  double val_fraction = 0.1;     // share of images listed in val_*.txt
  uint64_t seed = 0;             // split and noise are deterministic for a seed
  bool noise = true;
  int64_t size = 256;  // scene side (the display image is resized, aspect ignored)
  int workers = 0;     // <= 0: all cores
  bool progress = true;
  int64_t limit = 0;         // > 0: only the first `limit` images (sorted by name)
  std::string only = "all";  // all | train | val: simulate only that part of the split (lists keep the split)
  double exposure = 1.0;     // scene light relative to the display's (dim sets: < 1)
  bool lamp = false;         // one lamp per scene (lamp sets), lamp_gain x display white
  double lamp_gain = 20;
  std::string camera;  // what made the captures (the rig's path), recorded with the settings
  bool force = false;  // settings differ from the folder's record: rebuild (deletes its captures)
};

// A capture with more than this share of its pixels at full scale is counted as clipped.
inline constexpr double kClippedShare = 0.01;

struct SimulateReport {
  int64_t total = 0, simulated = 0, skipped = 0, train = 0, val = 0;
  // Of the captures simulated, those with more than kClippedShare of their pixels at the ADC's full
  // scale: light the sensor lost (scenes brighter than the camera's light unit holds).
  int64_t clipped = 0;
  double seconds = 0;  // wall time of the simulation loop
};

// Simulates every image not yet done (resumable: finished pairs are skipped; files appear
// atomically), then writes the lists. Errors name the first unreadable image. The settings that
// define the captures (photographs folder, camera, seed, noise, size, split, light) are recorded in
// OUT/simulate.yaml; a rerun with other settings is refused, naming them, unless `force`.
SimulateReport simulate_dataset(const Rig& rig, const SimulateOptions& options);

// The deterministic train/validation split `simulate_dataset` writes (and on-the-fly simulation
// uses): shuffle with the seed, the first round(fraction * n) are validation; both sorted.
std::pair<std::vector<std::string>, std::vector<std::string>> split_train_val(const std::vector<std::string>& names,
                                                                              double val_fraction, uint64_t seed);
// Writes train_meas/gt.txt and val_meas/gt.txt: the split_train_val split of all `names`, listing
// only the `complete` ones (a partially collected dataset is trainable, and its split is stable).
// Returns {train, val} counts listed.
std::pair<int64_t, int64_t> write_dataset_lists(const std::filesystem::path& out, const std::vector<std::string>& names,
                                                const std::vector<std::string>& complete, double val_fraction,
                                                uint64_t seed);
// The photographs of a folder (any image extension), split by split_train_val's rule:
// {train, held-out}. Errors when the folder has no readable images.
std::pair<std::vector<std::filesystem::path>, std::vector<std::filesystem::path>> split_image_files(
    const std::filesystem::path& dir, double val_fraction, uint64_t seed);
// The scene a display shows for a photograph: resized to size x size, quantised to 8 bits.
torch::Tensor display_scene(const std::filesystem::path& image, int64_t size);

}  // namespace flatnet
