#include "train/options.hpp"

namespace flatnet {

const std::vector<OptionField<MaskTrainOptions>>& mask_train_fields() {
  using O = MaskTrainOptions;
  static const std::vector<OptionField<O>> fields = {
      {"train.iterations", &O::iterations}, {"train.minutes", &O::minutes},       {"train.batch", &O::batch},
      {"train.optimizer", &O::optimizer},   {"train.lr", &O::lr},                 {"train.momentum", &O::momentum},
      {"train.gamma_init", &O::gamma_init}, {"train.val_every", &O::val_every},   {"train.log_every", &O::log_every},
      {"train.seed", &O::seed},
  };
  return fields;
}

const std::vector<OptionField<SeparableTrainOptions>>& separable_train_fields() {
  using O = SeparableTrainOptions;
  static const std::vector<OptionField<O>> fields = {
      {"data.images", &O::images},
      {"data.val_fraction", &O::val_fraction},
      {"data.split_seed", &O::split_seed},
      {"data.train_limit", &O::train_limit},
      {"codes.length", &O::code_length},
      {"codes.binary", &O::binary},
      {"codes.target_throughput", &O::target_throughput},
      {"codes.throughput_tolerance", &O::throughput_tolerance},
      {"train.iterations", &O::iterations},
      {"train.minutes", &O::minutes},
      {"train.batch", &O::batch},
      {"train.lr", &O::lr},
      {"train.lambda_init", &O::lambda_init},
      {"train.seed", &O::seed},
      {"train.log_every", &O::log_every},
      {"train.val_every", &O::val_every},
      {"train.val_count", &O::val_count},
  };
  return fields;
}

}  // namespace flatnet
