#include "train/options.hpp"

namespace flatnet {

const std::vector<OptionField<TrainOptions>>& train_fields() {
  using O = TrainOptions;
  static const std::vector<OptionField<O>> fields = {
      {"train.iterations", &O::iterations},
      {"train.minutes", &O::minutes},
      {"train.batch", &O::batch},
      {"train.lr", &O::lr},
      {"train.lr_discriminator", &O::lr_discriminator},
      {"train.lr_inversion_scale", &O::lr_inversion_scale},
      {"train.lr_halve_every", &O::lr_halve_every},
      {"train.ema_decay", &O::ema_decay},
      {"train.crop", &O::crop},
      {"train.discriminator_warmup", &O::discriminator_warmup},
      {"train.noise_augment", &O::noise_augment},
      {"train.seed", &O::seed},
      {"train.workers", &O::workers},
      {"train.val_every", &O::val_every},
      {"train.log_every", &O::log_every},
      {"train.channels_last", &O::channels_last},
      {"train.gemm_upsample", &O::gemm_upsample},
      {"train.check_sync_every", &O::check_sync_every},
      {"loss.mse", &O::w_mse},
      {"loss.ssim", &O::w_ssim},
      {"loss.perceptual", &O::w_perceptual},
      {"loss.adversarial", &O::w_adversarial},
      {"loss.feature_matching", &O::w_feature_matching},
      {"loss.frequency", &O::w_frequency},
      {"loss.chroma", &O::w_chroma},
      {"loss.gradient", &O::w_gradient},
      {"discriminator.real_label_min", &O::real_label_min},
      {"discriminator.fake_label_max", &O::fake_label_max},
  };
  return fields;
}

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

const std::vector<OptionField<LightAugment>>& light_fields() {
  using O = LightAugment;
  static const std::vector<OptionField<O>> fields = {
      {"exposure_probability", &O::exposure_probability}, {"exposure_min", &O::exposure_min},
      {"exposure_max", &O::exposure_max},                 {"lamp_probability", &O::lamp_probability},
      {"lamp_min", &O::lamp_min},                         {"lamp_max", &O::lamp_max},
  };
  return fields;
}

const std::vector<OptionField<CodesignOptions>>& codesign_fields() {
  using O = CodesignOptions;
  static const std::vector<OptionField<O>> fields = {
      {"lr", &O::lr},
      {"binary", &O::binary},
      {"target_throughput", &O::target_throughput},
      {"throughput_tolerance", &O::throughput_tolerance},
      {"freeze_at", &O::freeze_at},
      {"calib_error", &O::calib_error},
  };
  return fields;
}

const std::vector<OptionField<MaskOptions>>& mask_fields() {
  using O = MaskOptions;
  static const std::vector<OptionField<O>> fields = {
      {"elements", &O::elements}, {"rank", &O::rank},     {"upsample", &O::upsample},
      {"target_throughput", &O::target}, {"binary", &O::binary},
  };
  return fields;
}

const std::vector<OptionField<WienerCamera>>& wiener_camera_fields() {
  using O = WienerCamera;
  static const std::vector<OptionField<O>> fields = {
      {"rows", &O::rows}, {"cols", &O::cols}, {"scene", &O::scene}, {"noise_sigma", &O::noise_sigma},
      {"photons", &O::photons},
  };
  return fields;
}

}  // namespace flatnet
