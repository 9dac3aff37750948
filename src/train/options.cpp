#include "train/options.hpp"

namespace flatnet {

namespace {

// Ranges shared by many rows ("lo, hi, what it means").
constexpr double kBig = 1e9;
#define STEPS(what) 1, kBig, what
#define WEIGHT 0, 1e6, "a weight, 0 or more"
#define SHARE 0, 1, "0 to 1"

}  // namespace

const std::vector<OptionField<TrainOptions>>& train_fields() {
  using O = TrainOptions;
  static const std::vector<OptionField<O>> fields = {
      {"train.iterations", &O::iterations, STEPS("1 to 1e9 steps"), "optimiser steps (when train.minutes is 0)",
       "iterations"},
      {"train.minutes", &O::minutes, 0, 1e6,
       "0 (steps end the run) or minutes of wall-clock training (the run's length)",
       "wall-clock budget, resumes included; when > 0 it alone ends the run", "minutes"},
      {"train.batch", &O::batch, 1, 4096, "1 to 4096 samples", "scenes per step", "batch"},
      {"train.lr", &O::lr, 0, 10, "0 (frozen) to 10", "Adam, generator", "lr"},
      {"train.precision", &O::precision, 0, 0, "", "auto (bf16 where the CPU has AMX or AVX512-BF16) | fp32 | bf16",
       "precision"},
      {"train.lr_discriminator", &O::lr_discriminator, 0, 10, "0 (frozen) to 10", "Adam, discriminator"},
      {"train.lr_inversion_scale", &O::lr_inversion_scale, 0, 1e6, "0 (frozen inversion) or a positive factor",
       "the inversion's learning rate relative to lr"},
      {"train.lr_halve_every", &O::lr_halve_every, STEPS("1 or more steps"), "steps between halvings"},
      {"train.ema_decay", &O::ema_decay, 0, 0.999999, "0 (off) or a decay below 1",
       "moving average of the generator's weights"},
      {"train.crop", &O::crop, 0, 65536, "0 (whole scenes) or a crop size", "the enhancer's training windows"},
      {"train.discriminator_warmup", &O::discriminator_warmup, 0, kBig, "0 or more steps",
       "steps that train only the discriminator"},
      {"train.noise_augment", &O::noise_augment, 0, 10, "0 to 10 (a standard deviation)",
       "Gaussian noise added to the measurement"},
      {"train.seed", &O::seed, 0, 0, "", "initialisation, data order and augmentation"},
      {"train.workers", &O::workers, 1, 256, "1 to 256 data threads", "threads building batches"},
      {"train.val_every", &O::val_every, STEPS("1 or more steps"), "steps between validations"},
      {"train.val_count", &O::val_count, 0, kBig, "0 (all) or more images", "validation images"},
      {"train.log_every", &O::log_every, STEPS("1 or more steps"), "steps between log lines"},
      {"train.channels_last", &O::channels_last, 0, 0, "", "NHWC activations"},
      {"train.gemm_upsample", &O::gemm_upsample, 0, 0, "", "transposed convolutions as GEMMs"},
      {"train.check_sync_every", &O::check_sync_every, 0, kBig, "0 (off) or a number of steps",
       "distributed: verify identical parameters"},
      {"loss.mse", &O::w_mse, WEIGHT, "pixel MSE"},
      {"loss.ssim", &O::w_ssim, WEIGHT, "1 - SSIM"},
      {"loss.perceptual", &O::w_perceptual, WEIGHT, "VGG-16 features"},
      {"loss.adversarial", &O::w_adversarial, WEIGHT, "the generator's BCE against real"},
      {"loss.feature_matching", &O::w_feature_matching, WEIGHT, "the discriminator's features"},
      {"loss.frequency", &O::w_frequency, WEIGHT, "focal frequency loss"},
      {"loss.chroma", &O::w_chroma, WEIGHT, "CIELAB a*, b*"},
      {"loss.gradient", &O::w_gradient, WEIGHT, "image differences"},
      {"loss.stripe", &O::w_stripe, WEIGHT, "the error's row and column means less their trend"},
      {"discriminator.real_label_min", &O::real_label_min, SHARE, "real targets ~ U(min, 1)"},
      {"discriminator.fake_label_max", &O::fake_label_max, SHARE, "fake targets ~ U(0, max)"},
  };
  return fields;
}

const std::vector<OptionField<DataOptions>>& data_fields() {
  using O = DataOptions;
  static const std::vector<OptionField<O>> fields = {
      {"source", &O::source, 0, 0, "", "dataset (pairs on disk) | simulate (photographs through the rig)"},
      {"camera", &O::camera, 0, 0, "", "the camera .yaml: preprocessing, calibration, rig"},
      {"dataset", &O::dataset, 0, 0, "", "a folder `flatnet simulate` or capture-dataset wrote"},
      {"images", &O::images, 0, 0, "", "simulate: folder of photographs"},
      {"root", &O::root, 0, 0, "", "the folder FlatNet's list files are relative to"},
      {"train_meas", &O::train_meas, 0, 0, "", "FlatNet list file of training captures"},
      {"train_gt", &O::train_gt, 0, 0, "", "FlatNet list file of training scenes"},
      {"val_meas", &O::val_meas, 0, 0, "", "FlatNet list file of validation captures"},
      {"val_gt", &O::val_gt, 0, 0, "", "FlatNet list file of validation scenes"},
      {"val_fraction", &O::val_fraction, SHARE, "simulate: share of photographs held out"},
      {"split_seed", &O::split_seed, 0, 0, "", "simulate: seed of that split"},
  };
  return fields;
}

const std::vector<OptionField<PerceptualOptions>>& perceptual_fields() {
  using O = PerceptualOptions;
  static const std::vector<OptionField<O>> fields = {
      {"vgg_file", &O::vgg_file, 0, 0, "", "VGG-16 features (models/convert_vgg16.py)"},
      {"vgg_normalize", &O::vgg_normalize, 0, 0, "", "ImageNet mean/std before VGG"},
  };
  return fields;
}

const std::vector<OptionField<MaskTrainOptions>>& mask_train_fields() {
  using O = MaskTrainOptions;
  static const std::vector<OptionField<O>> fields = {
      {"train.iterations", &O::iterations, STEPS("1 to 1e9 steps")},
      {"train.minutes", &O::minutes, 0, 1e6,
       "0 (steps end the run) or minutes of wall-clock training (the run's length)"},
      {"train.batch", &O::batch, 1, 4096, "1 to 4096 samples"},
      {"train.optimizer", &O::optimizer, 0, 0, "", "sgd | adam"},
      {"train.lr", &O::lr, 0, 10, "0 (frozen) to 10"},
      {"train.momentum", &O::momentum, SHARE},
      {"train.gamma_init", &O::gamma_init, 1e-30, 1e6, "a positive regulariser", "Wiener regulariser's start"},
      {"train.val_every", &O::val_every, STEPS("1 or more steps")},
      {"train.log_every", &O::log_every, STEPS("1 or more steps")},
      {"train.seed", &O::seed},
  };
  return fields;
}

const std::vector<OptionField<PhotoSplit>>& photo_split_fields() {
  using O = PhotoSplit;
  static const std::vector<OptionField<O>> fields = {
      {"data.images", &O::images, 0, 0, "", "photographs (the training side of simulate's split)"},
      {"data.val_fraction", &O::val_fraction, SHARE, "share of the photographs held out"},
      {"data.split_seed", &O::split_seed, 0, 0, "", "seed of that split"},
      {"data.train_limit", &O::train_limit, 0, kBig, "0 (all) or more photographs", "photographs trained on"},
      {"train.val_count", &O::val_count, 0, kBig, "0 (all) or more images", "validation photographs"},
  };
  return fields;
}

const std::vector<OptionField<SeparableTrainOptions>>& separable_train_fields() {
  using O = SeparableTrainOptions;
  static const std::vector<OptionField<O>> fields = {
      {"data.images", &O::images, 0, 0, "", "photographs (the training side of simulate's split)", "images"},
      {"data.val_fraction", &O::val_fraction, SHARE},
      {"data.split_seed", &O::split_seed},
      {"data.train_limit", &O::train_limit, 0, kBig, "0 (all) or more photographs", "photographs trained on (0: all)",
       "train-limit"},
      {"codes.length", &O::code_length, 2, 65536, "2 or more elements"},
      {"codes.binary", &O::binary, 0, 0, "", "sign(u), sign(v) forward, straight-through gradients (a fabricable mask)",
       "binary"},
      {"codes.target_throughput", &O::target_throughput, 1e-3, 1, "a share of light, above 0 and at most 1"},
      {"codes.throughput_tolerance", &O::throughput_tolerance, SHARE},
      {"train.iterations", &O::iterations, STEPS("1 to 1e9 steps"), "optimiser steps (when train.minutes is 0)",
       "iterations"},
      {"train.minutes", &O::minutes, 0, 1e6,
       "0 (steps end the run) or minutes of wall-clock training (the run's length)"},
      {"train.batch", &O::batch, 1, 4096, "1 to 4096 samples", "photographs per step", "batch"},
      {"train.lr", &O::lr, 0, 10, "0 (frozen) to 10", "Adam, on the codes' pre-activations", "lr"},
      {"train.lambda_init", &O::lambda_init, 1e-12, 1e6, "a positive regulariser",
       "Tikhonov regulariser's start (learned)", "lambda"},
      {"train.seed", &O::seed, 0, 0, "", "initialisation and data order", "seed"},
      {"train.log_every", &O::log_every, STEPS("1 or more steps")},
      {"train.val_every", &O::val_every, STEPS("1 or more steps")},
      {"train.val_count", &O::val_count, 0, kBig, "0 (all) or more images", "validation photographs", "val-count"},
  };
  return fields;
}

const std::vector<OptionField<LightAugment>>& light_fields() {
  using O = LightAugment;
  static const std::vector<OptionField<O>> fields = {
      {"exposure_probability", &O::exposure_probability, 0, 1, "a probability, 0 to 1"},
      {"exposure_min", &O::exposure_min, 1e-6, 1e6, "a positive factor"},
      {"exposure_max", &O::exposure_max, 1e-6, 1e6, "a positive factor"},
      {"lamp_probability", &O::lamp_probability, 0, 1, "a probability, 0 to 1"},
      {"lamp_min", &O::lamp_min, 1e-6, 1e6, "a positive factor"},
      {"lamp_max", &O::lamp_max, 1e-6, 1e6, "a positive factor"},
  };
  return fields;
}

const std::vector<OptionField<CodesignOptions>>& codesign_fields() {
  using O = CodesignOptions;
  static const std::vector<OptionField<O>> fields = {
      {"lr", &O::lr, 1e-9, 10, "a positive learning rate"},
      {"binary", &O::binary},
      {"target_throughput", &O::target_throughput, 1e-3, 1, "a share of light, above 0 and at most 1"},
      {"throughput_tolerance", &O::throughput_tolerance, SHARE},
      {"freeze_at", &O::freeze_at, 0, 1, "a share of the run, 0 to 1"},
      {"calib_error", &O::calib_error, 0, 1, "0 to 1 (0.03: 3 %)"},
  };
  return fields;
}

const std::vector<OptionField<MaskOptions>>& mask_fields() {
  using O = MaskOptions;
  static const std::vector<OptionField<O>> fields = {
      {"elements", &O::elements, 2, 65536, "2 or more elements"},
      {"rank", &O::rank, 1, 511, "1 to 511"},
      {"upsample", &O::upsample, 1, 64, "1 to 64 sensor pixels per element"},
      {"target_throughput", &O::target, 1e-3, 1, "a share of light, above 0 and at most 1"},
      {"binary", &O::binary},
  };
  return fields;
}

const std::vector<OptionField<WienerCamera>>& wiener_camera_fields() {
  using O = WienerCamera;
  static const std::vector<OptionField<O>> fields = {
      {"rows", &O::rows, 1, 1e5, "a sensor size"},
      {"cols", &O::cols, 1, 1e5, "a sensor size"},
      {"scene", &O::scene, 1, 1e5, "a scene size"},
      {"noise_sigma", &O::noise_sigma, 0, 10, "0 to 10"},
      {"photons", &O::photons, 0, 1e12, "0 (off) or a photon count"},
  };
  return fields;
}

#undef STEPS
#undef WEIGHT
#undef SHARE

namespace {

// codes.init is "mls", "random" or a codes .mat: a path when it names a file (its reader decides).
const std::vector<RangeRow> kCodesInitRow = {{"codes.init", 0, 0, "", /*path=*/true}};

// Every table's ranges and path keys, registered with the config (io/config.hpp) at start-up.
const bool kRegistered = [] {
  register_ranges(range_rows(train_fields()));
  register_ranges(range_rows(data_fields(), "data."));
  register_ranges(range_rows(perceptual_fields(), "loss."));
  register_ranges(range_rows(mask_train_fields()));
  register_ranges(range_rows(photo_split_fields()));
  register_ranges(range_rows(separable_train_fields()));
  register_ranges(range_rows(light_fields(), "data.light."));
  register_ranges(range_rows(codesign_fields(), "codes."));
  register_ranges(range_rows(mask_fields(), "mask."));
  register_ranges(range_rows(wiener_camera_fields(), "camera."));
  register_ranges(kCodesInitRow);
  return true;
}();

}  // namespace

std::string codes_init_key() { return kCodesInitRow.front().key; }

}  // namespace flatnet
