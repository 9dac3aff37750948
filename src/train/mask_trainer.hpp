#pragma once
// Learning FlatCam masks end to end (FlatNet thesis, "learning the mask"): a rank-k mask, the
// lensless capture of grayscale scenes through its PSF, Wiener deconvolution with a learned
// regulariser gamma, and an MSE loss. The fair evaluation of any mask is eval/mask_score.
#include <filesystem>
#include <string>
#include <vector>

#include "optics/mask.hpp"
#include "train/loop.hpp"

namespace flatnet {

// The schedule (train/loop.hpp): 10,000 steps of 4 at lr 1e-4, validation every 500, a log row every
// 50; with train.minutes the run stops early, writing its mask.
struct MaskTrainOptions : Schedule {
  MaskTrainOptions() : Schedule{10000, 0, 4, 1e-4, 0, 500, 50, true} {}
  std::string optimizer = "sgd";  // sgd (thesis: momentum 0.5, lr 1e-4) | adam
  double momentum = 0.5;
  double gamma_init = 1e-6;   // Wiener regulariser to start from (MLS tunes to ~1e-6)
  std::filesystem::path out;  // mask.png, vectors.mat, gamma.txt, log.csv, val.csv, curve.png, latest.ckpt
  // Continue the run in `out` from its latest.ckpt (written at every validation, at the end and
  // when stopped early): the mask, the regulariser, the optimiser's state, the data order and the
  // logs up to that step, so that a resumed run takes the steps the straight run would have.
  bool resume = false;
  // With resume: continue a latest.ckpt of another run too (its run id differs from OUT/run_id.txt).
  bool force = false;
};

struct MaskTrainSummary {
  double gamma = 0, val_psnr = 0, throughput = 0, seconds = 0;
  int64_t steps = 0;
};

MaskTrainSummary train_mask(MaskModel& model, const torch::Tensor& train_scenes, const torch::Tensor& val_scenes,
                            const WienerCamera& cam, const MaskTrainOptions& options);

// Writes a mask window {rows, cols} in [0,1] as a 16-bit PNG (65535 = fully transparent).
void write_mask_png(const std::filesystem::path& path, const torch::Tensor& window);

}  // namespace flatnet
