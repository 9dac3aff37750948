#pragma once
// The trainers' option tables (io/option_table.hpp): TrainOptions, the mask and code-pair trainers', and
// the structs their configs also fill (the light augmentation, co-design, the mask, the Wiener
// camera). A test holds each struct's C++ defaults to its defaults file where they should agree.
#include <vector>

#include "io/option_table.hpp"
#include "optics/mask.hpp"
#include "optics/simulator.hpp"
#include "train/codesign.hpp"
#include "train/gan_trainer.hpp"
#include "train/mask_trainer.hpp"
#include "train/separable_trainer.hpp"

namespace flatnet {

// flatnet train: configs/defaults.yaml's train.*, loss.* and discriminator.* keys that map one to
// one onto TrainOptions (train.schedule and train.precision are parsed by train_options). Its
// C++ defaults are the library's (the thesis's recipe), not defaults.yaml's.
const std::vector<OptionField<TrainOptions>>& train_fields();
// mask train: configs/mask_defaults.yaml's train.* keys.
const std::vector<OptionField<MaskTrainOptions>>& mask_train_fields();
// mask separable: configs/separable_defaults.yaml (codes.init is resolved by the caller: mls, random or a file).
const std::vector<OptionField<SeparableTrainOptions>>& separable_train_fields();

// data.light.* (flatnet train): the random scene light.
const std::vector<OptionField<LightAugment>>& light_fields();
// codes.* (flatnet train with codes.learn): co-design's numbers (codes.init is resolved by the caller).
const std::vector<OptionField<CodesignOptions>>& codesign_fields();
// mask.* and camera.* (mask train; mask.projection, .throughput and .init are parsed by the caller).
const std::vector<OptionField<MaskOptions>>& mask_fields();
const std::vector<OptionField<WienerCamera>>& wiener_camera_fields();

}  // namespace flatnet
