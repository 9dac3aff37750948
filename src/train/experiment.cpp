#include "train/experiment.hpp"

#include <cmath>

#include <iostream>
#include <fstream>
#include <iomanip>
#include <optional>
#include <random>
#include <sstream>

#include "core/error.hpp"
#include "core/precision.hpp"
#include "core/util.hpp"
#include "io/dataset.hpp"
#include "nn/checkpoint.hpp"
#include "nn/model_file.hpp"
#include "optics/camera.hpp"
#include "optics/simulator.hpp"
#include "recon/data_consistency.hpp"
#include "train/options.hpp"
#include "train/run_id.hpp"

namespace flatnet {

namespace {

DataOptions data_options(const Config& c) {
  DataOptions d;
  read_options(c, data_fields(), d, "data.");
  return d;
}

// The rig the training captures come through: the camera's, with data.calibration_error's erring
// calibration when it is set (the network learns not to trust its first stage more than the camera
// deserves; validation keeps the camera's own rig).
std::shared_ptr<const Rig> training_rig(const std::shared_ptr<const Rig>& rig, const DataOptions& d) {
  if (!rig || d.calibration_error <= 0) return rig;
  auto erring = std::make_shared<Rig>(*rig);
  erring->bench.calibration_error = d.calibration_error;
  std::cerr << "data: each training capture through a calibration erring by " << 100 * d.calibration_error << " % ("
            << data_key(&DataOptions::calibration_error) << "), validation through the camera's own\n";
  return erring;
}

LightAugment light_options(const Config& c) {
  LightAugment light;
  read_options(c, light_fields(), light, "data.light.");
  return light;
}

// The width setting of the model's enhancer (what a user lowers when the model does not fit).
std::string enhancer_width_key(const ModelSpec& spec) {
  if (spec.enhancer == "dncnn") return model_key<&ModelSpec::dncnn, &DnCNNOptions::width>();
  if (spec.enhancer == "rcan") return model_key<&ModelSpec::rcan, &RCANOptions::width>();
  if (spec.enhancer == "nafnet") return model_key<&ModelSpec::nafnet, &NAFNetOptions::width>();
  return model_key<&ModelSpec::unet, &UNetOptions::width>();
}

// model.consistency's layer through the training camera's calibration (none when it is 0).
std::shared_ptr<const DataConsistency> consistency_layer(const Config& config, const ModelSpec& spec,
                                                         const CameraConfig& camera, const TrainOptions& opts) {
  const auto key = model_key(&ModelSpec::consistency_strength);
  const auto blur_key = model_key(&ModelSpec::consistency_blur);
  // One rule with infer and export: a blur where no step runs would do nothing, so it is refused.
  require(spec.consistency_blur == 0 || spec.consistency_strength > 0, blur_key,
          "blurs the data-consistency step's correction, and " + key +
              " is 0 (no step): set the strength too, or leave the blur at 0");
  if (spec.consistency_strength <= 0) return nullptr;
  const auto reach = consistency_blur_reach_problem(spec.consistency_blur, camera.scene_size);
  require(reach.empty(), blur_key, reach);
  require(!config.flag(codes_key(&CodesignOptions::learn)), key,
          "is not available with " + codes_key(&CodesignOptions::learn) + " (the calibration changes as it learns)");
  require(opts.crop == 0, train_key(&TrainOptions::crop),
          "must be 0 with " + key + ": the correction needs whole scenes");
  require(!camera.calibration.empty(), key, "corrects through the camera's calibration, and data.camera names none");
  return std::make_shared<const DataConsistency>(
      load_calibration(camera.calibration, camera), camera,
      DataConsistencyOptions{spec.consistency_strength, spec.consistency_blur});
}

}  // namespace

TrainOptions train_options(const Config& c, const std::filesystem::path& out) {
  TrainOptions t;
  read_options(c, train_fields(), t);  // each number already within its row's range (Config::load)
  require(t.crop == 0 || (t.crop >= 16 && t.crop % 16 == 0), train_key(&TrainOptions::crop),
          "must be 0 or a multiple of 16 (the U-Net halves it 4 times)");
  t.bf16 = resolve_precision(t.precision, option_key(train_key(&TrainOptions::precision))) == Precision::bf16;
  require(t.w_mse + t.w_perceptual + t.w_adversarial + t.w_ssim + t.w_feature_matching + t.w_frequency + t.w_chroma +
                  t.w_gradient + t.w_stripe + t.w_psnr + t.w_detail + t.w_random_features >
              0,
          "loss", "every weight is 0: nothing to train on");
  t.out = out;
  return t;
}

// Training and validation sources the config describes.
std::pair<std::shared_ptr<const PairSource>, std::shared_ptr<const PairSource>> data_sources(
    const Config& c, const CameraConfig& camera) {
  const auto d = data_options(c);
  const auto& source = d.source;
  if (source == "dataset") {
    require(d.val_light == ValidationLight::display, validation_light_key(),
            "judged validation lights photographs through the rig (data.source: simulate); a dataset's "
            "validation pairs are judged as they were captured");
    require(d.calibration_error == 0, data_key(&DataOptions::calibration_error),
            "errs the calibration photographs are simulated through (data.source: simulate); a dataset's "
            "captures are what they are");
    DatasetLists train, val;
    if (!d.dataset.empty()) {
      train = split_lists(d.dataset, "train");
      val = split_lists(d.dataset, "val");
    } else {
      require(!d.train_meas.empty(), "data",
              "set " + data_key(&DataOptions::dataset) + ", or the four list files (" +
                  data_key(&DataOptions::train_meas) + " ...)");
      train = {d.train_meas, d.train_gt, d.root};
      val = {d.val_meas, d.val_gt, d.root};
    }
    return {std::make_shared<DiskPairs>(read_pairs(train), camera),
            std::make_shared<DiskPairs>(read_pairs(val), camera)};
  }
  if (source == "simulate") {
    // Co-design captures through the codes it learns: no rig.
    const bool codesign = c.flag(codes_key(&CodesignOptions::learn));
    require(codesign || can_simulate(camera), data_key(&DataOptions::camera),
            "names no rig, and has no open_light to be simulated through its calibration; on-the-fly simulation "
            "needs one of them");
    require(!codesign || d.calibration_error == 0, data_key(&DataOptions::calibration_error),
            "is not available with " + codes_key(&CodesignOptions::learn) +
                " (the codes it learns are their own calibration; codes.calib_error is the written camera's)");
    auto rig = codesign ? nullptr : std::make_shared<const Rig>(load_camera_rig(camera));
    auto [train_images, val_images] = split_image_files(d.images, d.val_fraction, d.split_seed);
    const auto seed = static_cast<uint64_t>(c.integer(train_key(&TrainOptions::seed)));
    const auto light = light_options(c);
    require(light.exposure_min <= light.exposure_max && light.lamp_min <= light.lamp_max, "data.light",
            "needs exposure_min <= exposure_max and lamp_min <= lamp_max");
    // Validation on display captures (the held-out set's conditions), or on the three conditions the
    // evaluation sets judge (display, dim, lamp) in turn.
    return {std::make_shared<SimulatedPairs>(train_images, training_rig(rig, d), camera, seed, light),
            std::make_shared<SimulatedPairs>(val_images, rig, camera, seed + 1, LightAugment{},
                                             d.val_light == ValidationLight::judged)};
  }
  throw Error("config: data.source must be dataset or simulate, got '" + source + "'");
}

CodesignOptions codesign_options(const Config& c, const CameraConfig& camera) {
  CodesignOptions o;
  read_options(c, codesign_fields(), o, "codes.");
  require(!o.init_codes.empty(), codes_init_key(), "co-design starts from codes: mls or a codes .mat, not random");
  o.geometry = camera.raw;
  const auto camera_key = data_key(&DataOptions::camera);
  require(camera.scene_size == o.camera.scene, camera_key,
          "co-design builds the reference camera's sensor and optics, whose scene is " +
              std::to_string(o.camera.scene) + " pixels; this camera's is " + std::to_string(camera.scene_size));
  require(data_options(c).source == "simulate", codes_key(&CodesignOptions::learn),
          "needs data.source: simulate (photographs in data.images)");
  require(camera.raw.rotation == 0, camera_key,
          "co-design simulates unrotated captures; this camera's rotation is " + std::to_string(camera.raw.rotation));
  // Co-design builds its own optics from the codes it learns: a bench's errors would be dropped.
  require(!camera.bench.any(), camera_key,
          "co-design simulates the codes it learns on an ideal bench; this camera has a bench: section (" +
              printable(camera.name) + "): give a camera without one");
  return o;
}

namespace {

// Light augmentation redraws a simulated sample's light; captures on disk carry their own. A recipe
// made for simulation (the shipped models' configs) keeps its light settings when the user points it
// at a dataset, so they are turned off here, said in the log and recorded in config.yaml, instead of
// stopping the documented own-camera command (docs/own-camera.md step 4).
void light_off_for_captures_on_disk(Config& c, std::ostream& log) {
  const auto light = light_options(c);
  if (data_options(c).source != "dataset" || (light.exposure_probability <= 0 && light.lamp_probability <= 0)) return;
  c.set("data.light.exposure_probability=0", "data.source: dataset");
  c.set("data.light.lamp_probability=0", "data.source: dataset");
  log << "data.light: off (data.source: dataset: captures on disk carry their own light; light augmentation "
         "simulates samples from data.images)\n";
}

CameraConfig camera_of(const Config& c) { return load_camera_config(data_options(c).camera); }

// train.crop is a speed lever for large scenes: a recipe's crop (the shipped models' 128) on a camera
// whose scene is no larger trains on whole scenes, said in the log and recorded in config.yaml,
// instead of stopping a recipe the user only pointed at a smaller camera.
void whole_scenes_for_small_cameras(Config& c, const CameraConfig& camera, std::ostream& log) {
  const auto key = train_key(&TrainOptions::crop);
  const auto crop = c.integer(key);
  if (crop <= 0 || crop < camera.scene_size) return;
  c.set(key + "=0", "the camera's scene");
  log << key << ": 0 (whole scenes: " << crop << " is not below the camera's " << camera.scene_size
      << "-pixel scene)\n";
}

Vgg16Features vgg_if_needed(const Config& c, const TrainOptions& t) {
  if (t.w_perceptual <= 0) return Vgg16Features(nullptr);
  PerceptualOptions p;
  read_options(c, perceptual_fields(), p, "loss.");
  require(!p.vgg_file.empty(), key_of(perceptual_fields(), &PerceptualOptions::vgg_file, "loss."),
          "names no VGG-16 weights file, which " + train_key(&TrainOptions::w_perceptual) + " > 0 needs");
  return load_vgg16(p.vgg_file, p.vgg_normalize);
}

// "key (run: a, experiment.config: b), ..." for every setting in which two configs differ (paths compared
// resolved, as a checkpoint records them); empty when they agree.
std::string differing_settings(const Config& run, const Config& given) {
  const auto a = Config::from_text(run.to_yaml(), "run").values();
  const auto b = Config::from_text(given.to_yaml(), option_key("experiment.config")).values();
  std::string out;
  for (const auto& [key, value] : a) {
    const auto it = b.find(key);
    if (it != b.end() && it->second != value)
      out += (out.empty() ? "" : ", ") + key + " (run: " + value + ", " + option_key("experiment.config") + ": " +
             it->second + ")";
  }
  return out;
}

// The files a training run writes into its folder (that exist now).
std::vector<std::filesystem::path> run_files(const std::filesystem::path& out) {
  std::vector<std::filesystem::path> found;
  for (const char* name : {"latest.ckpt", "best.ckpt", "model.flatnet", "log.csv", "val.csv", "config.yaml",
                           "samples.png", "curve.png", "run_id.txt"})
    if (std::filesystem::exists(out / name)) found.push_back(out / name);
  // The run's kept models (train.keep_every): left beside a new run's, export --average-of would mix
  // two runs. A kept/ that is a link is the link alone: what it points to is not the run's.
  const auto kept = out / "kept";
  const auto kept_status = std::filesystem::symlink_status(kept);
  if (std::filesystem::is_symlink(kept_status)) {
    found.push_back(kept);
  } else if (std::filesystem::is_directory(kept_status)) {
    for (const auto& entry : std::filesystem::directory_iterator(kept)) {
      const auto name = entry.path().filename().string();
      if (name.rfind("step", 0) == 0 && entry.path().extension() == ".flatnet") found.push_back(entry.path());
    }
  }
  return found;
}

// Memory the machine can still give (MemAvailable), in bytes; 0 when unknown.
double available_memory_bytes() {
  std::ifstream in("/proc/meminfo");  // procfs reports size 0: read as a stream
  for (std::string key; in >> key;) {
    double kb = 0;
    in >> kb;
    if (key == "MemAvailable:") return kb * 1024;
    in.ignore(1 << 10, '\n');
  }
  return 0;
}

// --init-from: the model's generator into `g`; with --reinit inversion only its enhancer (and
// batch norm), the first stage as the config initialises it or, with init transfer, made to
// reproduce the model's first stage through this camera.
void initialise_from_model(const ExperimentOptions& o, const Config& config, const CameraConfig& camera, Generator& g,
                           std::ostream& log) {
  const auto spec = model_spec(config);
  const bool transfer = spec.inversion_init == "transfer";
  const auto source_model = load_model_file(o.init_from);  // read once: weights, spec and recorded camera
  init_generator_from(source_model, o.init_from, g, o.reinit_inversion ? GeneratorPart::enhancer : GeneratorPart::all);
  if (o.reinit_inversion)
    log << "initialised from " << o.init_from.string() << ": its enhancer (with the level path) and batch norm; "
        << "the first stage afresh for this camera (model.inversion.init " << spec.inversion_init
        << "); fresh optimisers and discriminator\n";
  else
    log << "initialised from " << o.init_from.string() << " (fresh optimisers)\n";
  // The step after the network is the config's to say: a model trained with it, fine-tuned without
  // it, learns to make pictures without the capture's help (and the reverse), so say which.
  const bool set_at_export = source_model.provenance.consistency == kConsistencySetAtExport;
  const auto from = set_at_export ? 0.0 : source_model.spec.consistency_strength;  // what its weights learned with
  if (set_at_export)
    log << "note: " << o.init_from.string() << " applies the data-consistency step c "
        << source_model.spec.consistency_strength << " set at export; its weights were trained without it ("
        << model_key(&ModelSpec::consistency_strength) << " 0)";
  else if (from != spec.consistency_strength)
    log << "note: " << o.init_from.string() << " was trained with " << model_key(&ModelSpec::consistency_strength)
        << " " << from;
  if (set_at_export || from != spec.consistency_strength)
    log << "; this run trains with " << spec.consistency_strength << " (its config's)\n";
  if (o.reinit_inversion && transfer) {
    auto source_camera = o.source_camera;
    if (source_camera.empty()) source_camera = source_model.recorded_camera();
    require_option(std::filesystem::exists(source_camera), "experiment.source_camera",
                   "the camera " + o.init_from.string() + " was trained for (" + source_camera.string() +
                       ") is not here; name its camera .yaml with " + option_key("experiment.source_camera"));
    const auto source = load_camera_config(source_camera);
    require(!source.calibration.empty() && !camera.calibration.empty(), "model.inversion.init",
            "transfer needs both cameras' calibrations");
    const auto old_calib = load_calibration(source.calibration, source);
    const auto new_calib = load_calibration(camera.calibration, camera);
    transfer_inversion(o.init_from, {old_calib.P, old_calib.Q, new_calib.P, new_calib.Q}, spec.inversion_lambda, g);
    log << "first stage transferred from " << o.init_from.string() << " (camera " << source_camera.string()
        << ") to this camera: W^T P_new ~ W_old^T P_old\n";
  }
}

}  // namespace

double training_bytes_per_sample(const ModelSpec& m, int64_t crop, const CameraConfig& camera) {
  const double side = static_cast<double>(crop > 0 ? crop : camera.scene_size);
  const double pixels = side * side;
  // Activations kept for the backward pass and their gradients, float32. Measured on the U-Net
  // (width 32, crop 128, the quality recipe): peak memory at batch 12 minus batch 4, over 8 samples,
  // is 71 MB, i.e. ~34 floats per first-level channel and pixel. DnCNN and RCAN keep about 8
  // floats per layer, channel and pixel (conv, batch norm, ReLU and their gradients).
  double floats = 0;
  if (m.enhancer == "dncnn")
    floats = 8.0 * m.dncnn.layers * m.dncnn.width * pixels;
  else if (m.enhancer == "rcan")
    floats = 8.0 * 3 * m.rcan.groups * m.rcan.blocks * m.rcan.width * pixels;
  else if (m.enhancer == "nafnet")  // ~40 floats per channel and pixel per block; each level has half the U-Net's
    floats = 40.0 * m.nafnet.width * pixels * 2 * (m.nafnet.enc_blocks + m.nafnet.dec_blocks + 1);
  else
    floats = 34.0 * m.unet.width * pixels;
  // The first stage: the measurement, W1^T Y and the scene, per Bayer plane, with gradients.
  const double rows = camera.raw.crop[2], cols = camera.raw.crop[3], n = camera.scene_size;
  floats += 3.0 * 4 * (rows * cols + n * cols + n * n);
  // The measurement pre-processor runs on the whole window, whatever the crop: each of its depth - 1
  // hidden layers keeps a convolution's and a leaky ReLU's output and their gradients.
  if (m.preprocessor_width > 0) floats += 4.0 * m.preprocessor_width * (m.preprocessor_depth - 1) * rows * cols;
  return 4.0 * floats;
}

// Memory a run holds whatever its batch: the generator's parameters with their gradients, Adam's two
// moments and the moving average (5 copies, float32). The U-Net's parameters grow with the square of
// its width: ~31 M at width 64 (Ronneberger et al.'s 64..1024), 124 M at the paper's 128.
double training_fixed_bytes(const ModelSpec& m, const CameraConfig& camera) {
  const auto square = [](double x) { return x * x; };
  double params = 0;
  if (m.enhancer == "dncnn")
    params = 9.0 * m.dncnn.layers * square(m.dncnn.width);
  else if (m.enhancer == "rcan")
    params = 2 * 9.0 * m.rcan.groups * m.rcan.blocks * square(m.rcan.width);
  else if (m.enhancer == "nafnet")
    params = 31e6 * square(m.nafnet.width / 64.0);
  else
    params = 31e6 * square(m.unet.width / 64.0);
  // The first stage: W1 {rows,N} and W2 {cols,N} per Bayer plane.
  params += 4.0 * (camera.raw.crop[2] + camera.raw.crop[3]) * camera.scene_size;
  // The pre-processor's 3x3 convolutions: 4 -> width, (depth - 2) x width -> width, width -> 4.
  const double w = static_cast<double>(m.preprocessor_width);
  if (w > 0) params += 9.0 * (8 * w + static_cast<double>(m.preprocessor_depth - 2) * w * w);
  return 5 * 4.0 * params;
}

namespace {

// The run's config: a resumed run's own (its checkpoint's, with experiment.sets on top; another
// experiment.config is refused), or a new run's (after checking that experiment.out holds no other run).
Config settle_config(const ExperimentOptions& o, bool writer, std::optional<double>& best_psnr) {
  const auto& out = o.out;
  const auto& sets = o.sets;
  const auto latest = out / "latest.ckpt";
  Config config;
  if (o.resume) {
    require(std::filesystem::exists(latest), latest, "nothing to resume (no checkpoint)");
    auto stored = checkpoint_settings(latest);  // one read: the run id and the settings
    if (!o.force) require_checkpoint_of_this_run(out, stored.run_id, latest, option_key("experiment.force"));
    // best.ckpt too: resume takes its best PSNR (read here, once), and export may take its weights.
    const auto best = out / "best.ckpt";
    if (std::filesystem::exists(best)) {
      const auto best_settings = checkpoint_settings(best);
      if (!o.force) require_checkpoint_of_this_run(out, best_settings.run_id, best, option_key("experiment.force"));
      best_psnr = best_settings.best_psnr;
    }
    config = std::move(stored.config);
    const auto val_light_key = validation_light_key();
    const auto stored_val_light = config.str(val_light_key);
    for (const auto& s : sets) config.set(s);
    config.check_ranges(option_key("experiment.sets"));
    // best.ckpt was picked on the run's validation: another validation's PSNR would not compare with
    // it, and the next validation would overwrite the run's best model.
    require_option(config.str(val_light_key) == stored_val_light || !std::filesystem::exists(best), "experiment.sets",
                   "changes " + val_light_key + " (run: " + stored_val_light + ") of a run whose " + best.string() +
                       " was picked on that validation; fork the run instead: copy its folder, delete the copy's "
                       "best.ckpt and resume the copy with the new setting");
    if (!o.config.empty()) {  // the same command line again is fine; another config is not silently ignored
      const auto differences = differing_settings(config, Config::load(o.config, sets));
      require_option(differences.empty(), "experiment.config",
                     option_key("experiment.resume") + " continues with the run's own config (" +
                         (out / "config.yaml").string() + "), which differs in " + differences +
                         "; change single settings with " + option_key("experiment.sets") + " key=value");
    }
    return config;
  }
  require(!writer || o.force || !std::filesystem::exists(latest), out,
          "already holds a training run; continue it with " + option_key("experiment.resume") + ", choose another " +
              option_key("experiment.out") + ", or set " + option_key("experiment.force") +
              " to "
              "start afresh (deleting it)");
  const auto old = run_files(out);
  if (writer && !o.force && !old.empty())
    throw Error(out, "holds the files of another run that never reached its first checkpoint (" +
                         old.front().filename().string() + " ...); set " + option_key("experiment.force") +
                         " to start afresh (deleting them) or choose another " + option_key("experiment.out"));
  // What --force removes is checked whole before any of it goes: a folder where a run keeps a file is
  // not the run's (a remove would fail halfway, the old run half gone).
  if (writer)
    for (const auto& f : old) {
      const auto status = std::filesystem::symlink_status(f);
      require(std::filesystem::is_regular_file(status) || std::filesystem::is_symlink(status), f,
              "is a folder (or not a plain file) where a run keeps a file; a new run neither removes nor replaces "
              "it: move it away, or choose another " +
                  option_key("experiment.out"));
    }
  return Config::load(o.config, sets);
}

// A model or batch that cannot fit is refused before it fills the machine's memory (an estimate;
// see training_bytes_per_sample).
void require_memory_for(const ModelSpec& spec, const CameraConfig& camera, const TrainOptions& opts) {
  const double available = available_memory_bytes();
  if (available <= 0) return;
  const double fixed = training_fixed_bytes(spec, camera);
  const auto gb = [](double bytes) { return std::to_string(static_cast<int64_t>(std::ceil(bytes / 1e9))); };
  require(fixed < 0.9 * available, enhancer_width_key(spec),
          "this model's weights, gradients and optimiser state need about " + gb(fixed) + " GB, and this machine has " +
              gb(available) + " GB available; choose a smaller width");
  const double need = fixed + training_bytes_per_sample(spec, opts.crop, camera) * static_cast<double>(opts.batch);
  require(need < 0.9 * available, train_key(&TrainOptions::batch),
          std::to_string(opts.batch) + " samples need about " + gb(need) + " GB for training (" + gb(fixed) +
              " of them for the model and its optimiser), and this machine has " + gb(available) +
              " GB available; lower train.batch (or train.crop" +
              (spec.preprocessor_width > 0
                   ? std::string(", or model.preprocessor.width and depth, which run on the whole window")
                   : std::string()) +
              ")");
}

}  // namespace

ExperimentResult run_experiment(const ExperimentOptions& o) {
  std::ostream& log = o.log ? *o.log : std::cerr;
  const auto& dist = o.distributed;
  require_option(!o.out.empty(), "experiment.out", "an output folder is required");
  require_option(dist.world_size >= 1 && dist.rank >= 0 && dist.rank < dist.world_size, "experiment.rank",
                 "must lie in [0, world size " + std::to_string(dist.world_size) + ")");
  const bool writer = dist.rank == 0;
  const auto& out = o.out;
  const auto latest = out / "latest.ckpt";
  const bool resume = o.resume;
  std::optional<double> best_psnr;  // best.ckpt's, read once on resume
  Config config = settle_config(o, writer, best_psnr);
  require_option(!(resume && !o.init_from.empty()), "experiment.init_from",
                 "starts a new run; it cannot be combined with " + option_key("experiment.resume"));
  light_off_for_captures_on_disk(config, log);
  // Everything that can fail on bad input is checked before anything is written.
  const auto camera = camera_of(config);
  whole_scenes_for_small_cameras(config, camera, log);
  auto opts = train_options(config, out);
  auto vgg = vgg_if_needed(config, opts);
  const auto spec = model_spec(config);
  require_memory_for(spec, camera, opts);
  const auto consistency = consistency_layer(config, spec, camera, opts);
  CodePairCamera learned{nullptr};  // co-design: the camera whose codes learn with the network
  CodesignOptions codesign;
  if (config.flag(codes_key(&CodesignOptions::learn))) {
    require(dist.world_size == 1, codes_key(&CodesignOptions::learn), "co-design runs in one process");
    codesign = codesign_options(config, camera);
    learned = CodePairCamera(codesign);
  }
  auto [train_src, val_src] = data_sources(config, camera);
  torch::manual_seed(opts.seed);
  require_option(!o.reinit_inversion || !o.init_from.empty(), "experiment.reinit",
                 "re-initialises part of a " + option_key("experiment.init_from") + " model");
  const bool transfer = spec.inversion_init == "transfer";
  require(!transfer || resume || o.reinit_inversion, "model.inversion.init",
          "transfer makes the first stage from a trained model's: use it with " + option_key("experiment.init_from") +
              " MODEL " + option_key("experiment.reinit") + " inversion");
  Generator g(generator_options(config, camera, !resume && (o.init_from.empty() || o.reinit_inversion)));
  if (!o.init_from.empty()) initialise_from_model(o, config, camera, g, log);

  if (writer) {
    const auto p = opts.bf16 ? Precision::bf16 : Precision::fp32;  // train_options resolved it for this CPU
    if (p == Precision::bf16) request_amx_permission();
    log << "precision: " << describe_precision(p) << "\n";
  }
  Discriminator d(discriminator_options(config));
  log << "loading " << (opts.val_count > 0 ? std::min(opts.val_count, val_src->size()) : val_src->size())
      << " validation samples...\n";
  auto val = load_all(*val_src, opts.val_count, std::max(1, opts.workers));
  if (writer && !resume)
    for (const auto& f : run_files(out)) std::filesystem::remove(f);  // --force: the old run's files go
  std::unique_ptr<ProcessGroup> group;
  if (dist.world_size > 1) {
    log << "rank " << dist.rank << " of " << dist.world_size << ": joining " << dist.master_addr << ":"
        << dist.master_port << "...\n";
    group = std::make_unique<ProcessGroup>(dist);
  }
  GanTrainer trainer(g, d, vgg, train_src, std::move(val), opts, model_identity(config, camera));
  if (learned) {
    log << "co-design: codes from " << config.str(codes_init_key()) << " (throughput "
        << learned->throughput().item<double>() << "), learned until " << codesign.freeze_at * 100
        << " % of the run; their camera in " << (out / "camera").string() << "\n";
    trainer.set_learned_camera(learned, camera);
  }
  if (consistency) {
    log << "data consistency: pictures corrected by their captures (c " << spec.consistency_strength << ", blur "
        << spec.consistency_blur << " px: the capture decides " << 100 * consistency->measured_share()
        << " % of singular pairs)\n";
    trainer.set_consistency(consistency);
  }
  if (resume)
    log << trainer.resume(latest, best_psnr) << "\n";  // every rank reads rank 0's checkpoint (a shared folder)
  if (trainer.run_id().empty()) trainer.set_run_id(new_run_id());  // a new run, or one from before run ids
  if (writer) {  // after a resume succeeded: a refused one changes nothing
    std::filesystem::create_directories(out);
    write_text_atomically(out / "config.yaml", config.to_yaml());
    record_run_id(out, trainer.run_id());
  }
  trainer.set_distributed(group.get());
  log << "training on " << train_src->size() << " pairs, "
      << (opts.minutes > 0 ? format_duration(60.0 * opts.minutes) + " (train.minutes)"
                           : std::to_string(opts.iterations) + " steps")
      << " of batch " << opts.batch
      << (dist.world_size > 1 ? " per rank x " + std::to_string(dist.world_size) + " ranks" : "") << " (" << spec.input
      << " + " << enhancer_text(spec) << ")\n";
  ExperimentResult result;
  result.writer = writer;
  result.summary = trainer.run();
  return result;
}

}  // namespace flatnet
