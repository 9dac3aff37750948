#pragma once
// The trainers' option tables (io/option_table.hpp): TrainOptions, the mask and code-pair trainers', and
// the structs their configs also fill (the light augmentation, co-design, the mask, the Wiener
// camera). A test holds each struct's C++ defaults to its defaults file where they should agree.
#include <filesystem>
#include <string>
#include <vector>

#include "io/option_table.hpp"
#include "optics/mask.hpp"
#include "optics/simulator.hpp"
#include "train/codesign.hpp"
#include "train/gan_trainer.hpp"
#include "train/mask_trainer.hpp"
#include "train/separable_trainer.hpp"

namespace flatnet {

// data.* of flatnet train: where the pairs come from.
struct DataOptions {
  std::string source = "dataset";  // dataset | simulate
  std::filesystem::path camera, dataset, images, root, train_meas, train_gt, val_meas, val_gt;
  double val_fraction = 0.1;
  int64_t split_seed = 1;
  ValidationLight val_light = ValidationLight::display;  // simulate: display | judged (kJudgedConditions in turn)
  // simulate: each training capture through a calibration that errs by this share of its coded light,
  // redrawn per capture (BenchErrors::calibration_error; validation keeps the camera's own). 0: the camera's.
  double calibration_error = 0;
};

// loss.vgg_file and loss.vgg_normalize: the perceptual loss's network.
struct PerceptualOptions {
  std::filesystem::path vgg_file;
  bool vgg_normalize = false;
};

// mask train: which photographs it trains and validates on (simulate's split).
struct PhotoSplit {
  std::filesystem::path images;
  double val_fraction = 0.1;
  int64_t split_seed = 1;
  int64_t train_limit = 0, val_count = 32;
};

// flatnet train: configs/defaults.yaml's train.*, loss.* and discriminator.* keys of TrainOptions
// (train.precision is resolved by train_options). Its C++ defaults are the library's (the thesis's
// recipe), not defaults.yaml's. The schedule rows (train.iterations, .minutes, .batch, .lr, .seed,
// .val_every, .log_every) are one table all three trainers share.
const std::vector<OptionField<TrainOptions>>& train_fields();
// data.* (prefix "data.") and loss.vgg_* (prefix "loss.") of flatnet train.
const std::vector<OptionField<DataOptions>>& data_fields();
const std::vector<OptionField<PerceptualOptions>>& perceptual_fields();
// mask train: configs/mask_defaults.yaml's train.* keys, and its photographs.
const std::vector<OptionField<PhotoSplit>>& photo_split_fields();
const std::vector<OptionField<MaskTrainOptions>>& mask_train_fields();
// mask separable: configs/separable_defaults.yaml (codes.init: mls, random or a codes .mat).
const std::vector<OptionField<SeparableTrainOptions>>& separable_train_fields();

// data.light.* (flatnet train): the random scene light.
const std::vector<OptionField<LightAugment>>& light_fields();
// codes.* (flatnet train; co-design with codes.learn).
const std::vector<OptionField<CodesignOptions>>& codesign_fields();
// mask.* and camera.* (mask train).
const std::vector<OptionField<MaskOptions>>& mask_fields();
const std::vector<OptionField<WienerCamera>>& wiener_camera_fields();

// codes.init: mls, random or a codes .mat.
std::string codes_init_key();
// data.val_light: display or judged (a choice row, which data_key cannot name).
std::string validation_light_key();

// Registers every table's ranges and path keys with the config (io/config.hpp), once: each program
// calls it at start-up (cli/main, the tests' main, the fuzz harnesses), before any config is read.
void register_option_tables();

// The key of the row binding a member, as errors name it: train_key(&TrainOptions::crop) is
// "train.crop".
template <class T>
std::string train_key(T TrainOptions::*member) {
  return key_of(train_fields(), member);
}
// The shared schedule's members (train_key(&TrainOptions::batch) names a Schedule member).
template <class T>
std::string train_key(T Schedule::*member) {
  return train_key(static_cast<T TrainOptions::*>(member));
}
template <class T>
std::string data_key(T DataOptions::*member) {
  return key_of(data_fields(), member, "data.");
}
template <class T>
std::string codes_key(T CodesignOptions::*member) {
  return key_of(codesign_fields(), member, "codes.");
}

}  // namespace flatnet
