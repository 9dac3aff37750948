#include "train/options.hpp"

#include "core/util.hpp"
#include "nn/model_spec.hpp"

namespace flatnet {

namespace {

// Ranges shared by many rows ("lo, hi, what it means").
constexpr double kBig = 1e9;
#define STEPS(what) 1, kBig, what
#define WEIGHT 0, 1e6, "a weight, 0 or more"
#define SHARE 0, 1, "0 to 1"

// The schedule every trainer shares (train.*): one row per key, whichever trainer reads it. O is a
// trainer's options (TrainOptions, MaskTrainOptions, SeparableTrainOptions), each with these members;
// each trainer's defaults file gives its own defaults.
template <class O>
std::vector<OptionField<O>> schedule_fields() {
  return {
      {"train.iterations", &O::iterations, STEPS("1 to 1e9 steps"), "iterations"},
      {"train.minutes", &O::minutes, 0, 1e6,
       "0 (steps end the run) or minutes of wall-clock training (the run's length)", "minutes"},
      {"train.batch", &O::batch, 1, 4096, "1 to 4096 samples", "batch"},
      {"train.lr", &O::lr, 0, 10, "0 (frozen) to 10", "lr"},
      {"train.seed", &O::seed, 0, 0, "", "seed"},
      {"train.val_every", &O::val_every, STEPS("1 or more steps")},
      {"train.log_every", &O::log_every, STEPS("1 or more steps")},
  };
}

// The photographs the mask and code-pair trainers read and validate on (simulate's split): O is
// PhotoSplit or SeparableTrainOptions.
template <class O>
std::vector<OptionField<O>> photo_fields() {
  return {
      {"data.images", &O::images, 0, 0, "", "images"},
      {"data.val_fraction", &O::val_fraction, SHARE},
      {"data.split_seed", &O::split_seed},
      {"data.train_limit", &O::train_limit, 0, kBig, "0 (all) or more photographs", "train-limit"},
      {"train.val_count", &O::val_count, 0, kBig, "0 (all) or more images", "val-count"},
  };
}

// A choice read by its parser (an enum's name): `parse(text, key)` names the key in its error, and the
// member compares as its number.
template <class O, class E, E O::*member, E (*parse)(const std::string&, const std::string&)>
Choice<O> choice() {
  return {[](const Config& c, const std::string& key, O& o) { o.*member = parse(c.str(key), key); },
          [](const O& o) { return std::to_string(static_cast<int>(o.*member)); }};
}

// codes.init: mls (the shipped MLS codes), random (none: the trainer draws them), or a codes .mat,
// resolved against the file that named it. O has init_codes.
template <class O>
Choice<O> codes_init_choice() {
  return {[](const Config& c, const std::string& key, O& o) {
            const auto text = c.str(key);
            o.init_codes = text == "mls"      ? data_dir() / "models" / "camera" / "codes_mls.mat"
                           : text == "random" ? std::filesystem::path()
                                              : c.path(key);
          },
          nullptr, /*path=*/true};
}
constexpr const char* kCodesInit = "init";
constexpr const char* kValidationLight = "val_light";

}  // namespace

const std::vector<OptionField<TrainOptions>>& train_fields() {
  using O = TrainOptions;
  static const std::vector<OptionField<O>> fields = joined(
      schedule_fields<O>(),
      {
          {"train.schedule", choice<O, LrSchedule, &O::schedule, parse_lr_schedule>()},
          {"train.precision", &O::precision, 0, 0, "", "precision"},
          {"train.lr_discriminator", &O::lr_discriminator, 0, 10, "0 (frozen) to 10"},
          {"train.lr_inversion_scale", &O::lr_inversion_scale, 0, 1e6, "0 (frozen inversion) or a positive factor"},
          {"train.lr_halve_every", &O::lr_halve_every, STEPS("1 or more steps")},
          {"train.ema_decay", &O::ema_decay, 0, 0.999999, "0 (off) or a decay below 1"},
          {"train.keep_every", &O::keep_every, 0, kBig, "0 (off) or a number of steps"},
          {"train.bn_refresh", &O::bn_refresh, 0, 100000, "0 (off) to 100000 batches"},
          {"train.save_minutes", &O::save_minutes, 0, 1e6, "0 (off) or minutes between saves of latest.ckpt"},
          {"train.crop", &O::crop, 0, 65536, "0 (whole scenes) or a crop size"},
          {"train.discriminator_warmup", &O::discriminator_warmup, 0, kBig, "0 or more steps"},
          {"train.noise_augment", &O::noise_augment, 0, 10, "0 to 10 (a standard deviation)"},
          {"train.workers", &O::workers, 1, 256, "1 to 256 data threads"},
          {"train.val_count", &O::val_count, 0, kBig, "0 (all) or more images"},
          {"train.channels_last", &O::channels_last},
          {"train.gemm_upsample", &O::gemm_upsample},
          {"train.check_sync_every", &O::check_sync_every, 0, kBig, "0 (off) or a number of steps"},
          {"loss.mse", &O::w_mse, WEIGHT},
          {"loss.ssim", &O::w_ssim, WEIGHT},
          {"loss.perceptual", &O::w_perceptual, WEIGHT},
          {"loss.adversarial", &O::w_adversarial, WEIGHT},
          {"loss.feature_matching", &O::w_feature_matching, WEIGHT},
          {"loss.frequency", &O::w_frequency, WEIGHT},
          {"loss.chroma", &O::w_chroma, WEIGHT},
          {"loss.gradient", &O::w_gradient, WEIGHT},
          {"loss.stripe", &O::w_stripe, WEIGHT},
          {"loss.psnr", &O::w_psnr, WEIGHT},
          {"loss.detail", &O::w_detail, WEIGHT},
          {"loss.random_features", &O::w_random_features, WEIGHT},
          {"discriminator.real_label_min", &O::real_label_min, SHARE},
          {"discriminator.fake_label_max", &O::fake_label_max, SHARE},
      });
  return fields;
}

const std::vector<OptionField<DataOptions>>& data_fields() {
  using O = DataOptions;
  static const std::vector<OptionField<O>> fields = {
      {"source", &O::source},
      {"camera", &O::camera},
      {"dataset", &O::dataset},
      {"images", &O::images},
      {"root", &O::root},
      {"train_meas", &O::train_meas},
      {"train_gt", &O::train_gt},
      {"val_meas", &O::val_meas},
      {"val_gt", &O::val_gt},
      {"val_fraction", &O::val_fraction, SHARE},
      {"split_seed", &O::split_seed},
      {kValidationLight, choice<O, ValidationLight, &O::val_light, parse_validation_light>()},
      {"calibration_error", &O::calibration_error, 0, 0.5, "a share of the coded light, 0 to 0.5 (0.1: 10 %)"},
  };
  return fields;
}

const std::vector<OptionField<PerceptualOptions>>& perceptual_fields() {
  using O = PerceptualOptions;
  static const std::vector<OptionField<O>> fields = {
      {"vgg_file", &O::vgg_file},
      {"vgg_normalize", &O::vgg_normalize},
  };
  return fields;
}

const std::vector<OptionField<MaskTrainOptions>>& mask_train_fields() {
  using O = MaskTrainOptions;
  static const std::vector<OptionField<O>> fields =
      joined(schedule_fields<O>(), {
                                       {"train.optimizer", &O::optimizer},
                                       {"train.momentum", &O::momentum, SHARE},
                                       {"train.gamma_init", &O::gamma_init, 1e-30, 1e6, "a positive regulariser"},
                                   });
  return fields;
}

const std::vector<OptionField<PhotoSplit>>& photo_split_fields() {
  using O = PhotoSplit;
  static const std::vector<OptionField<O>> fields = photo_fields<O>();
  return fields;
}
const std::vector<OptionField<SeparableTrainOptions>>& separable_train_fields() {
  using O = SeparableTrainOptions;
  static const std::vector<OptionField<O>> fields =
      joined(joined(schedule_fields<O>(), photo_fields<O>()),
             {
                 {"codes.init", codes_init_choice<O>(), 0, 0, "", "init"},
                 {"codes.length", &O::code_length, 2, 65536, "2 or more elements"},
                 {"codes.binary", &O::binary, 0, 0, "", "binary"},
                 {"codes.target_throughput", &O::target_throughput, 1e-3, 1, "a share of light, above 0 and at most 1"},
                 {"codes.throughput_tolerance", &O::throughput_tolerance, SHARE},
                 {"train.lambda_init", &O::lambda_init, 1e-12, 1e6, "a positive regulariser", "lambda"},
             });
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
      {"learn", &O::learn},
      {kCodesInit, codes_init_choice<O>()},
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
      {"projection", choice<O, MaskProjection, &O::projection, parse_mask_projection>()},
      {"throughput", choice<O, ThroughputRule, &O::throughput, parse_throughput_rule>()},
      {"init", choice<O, MaskInit, &O::init, parse_mask_init>()},
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
      {"noise_sigma", &O::noise_sigma, 0, 10, "0 to 10 (0 needs camera.photons above 0)"},
      {"photons", &O::photons, 0, 1e12, "0 (off) or a photon count"},
  };
  return fields;
}

#undef STEPS
#undef WEIGHT
#undef SHARE

void register_option_tables() {
  static const bool registered = [] {
    register_model_option_tables();
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
    return true;
  }();
  (void)registered;
}

std::string codes_init_key() { return std::string("codes.") + kCodesInit; }
std::string validation_light_key() { return std::string("data.") + kValidationLight; }

}  // namespace flatnet
