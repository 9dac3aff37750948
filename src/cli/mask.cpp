// flatnet mask train | eval | report: learned FlatCam masks against MLS and FlatNet's 02 mask.
#include <fstream>
#include <iomanip>
#include <iostream>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "core/util.hpp"
#include "core/precision.hpp"
#include "eval/mask_report.hpp"
#include "eval/metrics.hpp"
#include "eval/plot.hpp"
#include "eval/tables.hpp"
#include "optics/separable_camera.hpp"
#include "io/image.hpp"
#include "io/mat.hpp"
#include "optics/codes.hpp"
#include "optics/simulator.hpp"
#include "io/config.hpp"
#include "eval/mask_score.hpp"
#include "train/mask_trainer.hpp"
#include "train/options.hpp"
#include "nn/model_file.hpp"
#include "train/separable_trainer.hpp"
#include "train/trainer_checkpoint.hpp"

namespace flatnet::cli {

namespace {

std::filesystem::path mask_defaults() { return data_dir() / "configs" / "mask_defaults.yaml"; }
std::filesystem::path separable_defaults() { return data_dir() / "configs" / "separable_defaults.yaml"; }

WienerCamera wiener_camera(const Config& c) {
  WienerCamera cam;
  read_options(c, wiener_camera_fields(), cam, "camera.");
  require(cam.scene <= cam.rows && cam.scene <= cam.cols, "camera.scene", "must fit in the sensor");
  return cam;
}

std::vector<std::filesystem::path> first(const std::vector<std::filesystem::path>& v, int64_t n) {
  return n <= 0 || n >= static_cast<int64_t>(v.size()) ? v
                                                       : std::vector<std::filesystem::path>(v.begin(), v.begin() + n);
}

// The mask and code-pair trainers' run flags (their settings are their config's rows).
struct TrainerRun {
  std::filesystem::path config, out;
  std::vector<std::string> set;  // --set key=value, repeatable, in order
  bool resume = false, force = false;
};

const FlagTable<TrainerRun>& trainer_run_flags() {
  using S = TrainerRun;
  static const FlagTable<S> rows = {
      {"config", &S::config, "experiment config overriding the trainer's defaults file (configs/mask_rank1.yaml, ...)"},
      {"set", &S::set, "override a setting, key=value (repeatable)"},
      {"out", &S::out, "output folder (the run: config.yaml, latest.ckpt, log.csv, what it learned)"},
      {"resume", &S::resume,
       "continue the run in --out from its latest.ckpt, with its own config (--set and the shortcut flags change "
       "single settings)"},
      {"force", &S::force, "start afresh in an --out folder that holds another run"},
  };
  return rows;
}

// The config of a trainer's run in `out`: with --resume the run's own (out/config.yaml) under
// `sets`, else --config's or the defaults'. Refuses --resume without a checkpoint or with --config,
// and a new run over a run's checkpoint without --force; `run` names the run in that message.
Config run_config(const TrainerRun& flags, const std::vector<std::string>& sets, const std::filesystem::path& defaults,
                  const std::string& run) {
  const auto& out = flags.out;
  require(!flags.resume || flags.config.empty(), "--resume",
          "continues with the run's own config (" + (out / "config.yaml").string() +
              "); change single settings with --set");
  require(!flags.resume || has_trainer_checkpoint(out), out / "latest.ckpt", "nothing to resume (no checkpoint)");
  require(flags.resume || flags.force || !has_trainer_checkpoint(out), out,
          "already holds a " + run + "; continue it with --resume, or start afresh with --force");
  return flags.resume ? Config::load(out / "config.yaml", sets, defaults) : Config::load(flags.config, sets, defaults);
}

int mask_train(int argc, char** argv) {
  cxxopts::Options o("flatnet mask train", "Learn a rank-k amplitude mask end to end through Wiener deconvolution.");
  add_flags(o, trainer_run_flags());
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("out"), "mask train", "--out DIR is required");
  TrainerRun run;
  read_flags(r, trainer_run_flags(), run);
  const auto& out = run.out;
  const bool resume = run.resume;
  const auto c = run_config(run, run.set, mask_defaults(), "mask training run");
  MaskOptions mo;
  read_options(c, mask_fields(), mo, "mask.");
  MaskTrainOptions to;
  read_options(c, mask_train_fields(), to);
  mo.seed = to.seed;
  const auto cam = wiener_camera(c);
  mo.rows = cam.rows;
  mo.cols = cam.cols;
  to.out = out;
  to.resume = resume;
  to.force = run.force;
  require(to.gamma_init > 0, "train.gamma_init", "must be positive");
  MaskModel model(mo);  // validates rank, projection, throughput rule
  PhotoSplit photos;
  read_options(c, photo_split_fields(), photos);
  auto [train_imgs, val_imgs] = split_image_files(photos.images, photos.val_fraction, photos.split_seed);
  std::cerr << "loading " << first(train_imgs, photos.train_limit).size() << " training and "
            << first(val_imgs, photos.val_count).size() << " validation photographs...\n";
  const auto train = load_luma_scenes(first(train_imgs, photos.train_limit), cam.scene, 2);
  const auto val = load_luma_scenes(first(val_imgs, photos.val_count), cam.scene, 2);
  const auto claim = claim_out(r, to.out, "mask train");
  write_text_atomically(to.out / "config.yaml", c.to_yaml());
  watch_interrupts();
  const auto s = train_mask(model, train, val, cam, to);
  std::cout << "rank " << mo.rank << " mask: validation PSNR " << std::fixed << std::setprecision(2) << s.val_psnr
            << " dB, throughput " << std::setprecision(3) << s.throughput << ", gamma " << std::scientific
            << std::setprecision(3) << s.gamma << std::defaultfloat << " after " << s.steps << " steps in "
            << format_duration(s.seconds) << "\nwrote " << (to.out / "mask.png").string()
            << ", vectors.mat, gamma.txt, log.csv, curve.png, latest.ckpt\n";
  if (interrupted())
    std::cerr << "interrupted: continue with `flatnet mask train --out " << to.out.string() << " --resume`\n";
  return interrupted() ? 130 : 0;
}

// The settings of `flatnet mask eval`.
struct MaskEvalSettings {
  std::string mask;  // mask.png, mls or m02
  std::filesystem::path images;
  double noise = WienerCamera{}.noise_sigma;
  int64_t count = 0;
};

const FlagTable<MaskEvalSettings>& mask_eval_flags() {
  using S = MaskEvalSettings;
  static const FlagTable<S> rows = {
      {"mask", &S::mask, "mask.png (16-bit, 65535 = transparent), mls or m02"},
      {"images", &S::images, "photographs: gamma is tuned on the first quarter, PSNR measured on the rest"},
      {"noise", &S::noise, "Gaussian noise sigma", 1e-12, 1, "a positive sigma up to 1"},
      {"count", &S::count, "use at most this many photographs (0: all)", 0, 1e12, "0 (all) or more"},
  };
  return rows;
}

// gamma tuned on the first quarter, PSNR on the rest.
int mask_eval(int argc, char** argv) {
  cxxopts::Options o("flatnet mask eval", "Throughput, tuned gamma and mean PSNR of a mask under the Wiener protocol.");
  add_flags(o, mask_eval_flags());
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("mask") && r.count("images"), "mask eval", "--mask and --images are required");
  MaskEvalSettings set;
  read_flags(r, mask_eval_flags(), set);
  WienerCamera cam;
  cam.noise_sigma = set.noise;
  const auto window = load_mask_window(set.mask, cam);
  require(window.min().item<double>() >= 0 && window.max().item<double>() <= 1, set.mask,
          "transmittance outside [0, 1]");
  const auto images = first(list_images(set.images, kImageExtensions), set.count);
  require(images.size() >= 2, set.images, "needs at least 2 readable images");
  const auto scenes = load_luma_scenes(images, cam.scene, 2);
  const int64_t n_tune = std::max<int64_t>(1, scenes.size(0) / 4);
  const double gamma = tune_gamma(window, scenes.slice(0, 0, n_tune), cam, 777);
  const double psnr = mask_psnr(window, gamma, scenes.slice(n_tune), cam, 4242);
  std::cout << "mask " << set.mask << ": throughput " << std::setprecision(4) << throughput(window) << ", gamma "
            << std::scientific << std::setprecision(3) << gamma << std::defaultfloat << " (tuned on " << n_tune
            << " images), PSNR " << std::fixed << std::setprecision(2) << psnr << " dB on " << scenes.size(0) - n_tune
            << " images at sigma " << std::scientific << std::setprecision(1) << cam.noise_sigma << "\n";
  return 0;
}

std::filesystem::path shipped(const std::string& relative) { return data_dir() / relative; }

// A path as a report shows it: relative to the source tree when inside it.
std::string shown(const std::filesystem::path& p) {
  const auto rel =
      std::filesystem::weakly_canonical(p).lexically_relative(std::filesystem::weakly_canonical(data_dir()));
  return !rel.empty() && *rel.begin() != ".." ? rel.string() : p.string();
}

// mask report's flags: the library's options with the lists that build them.
struct MaskReportSettings : MaskReportOptions {
  std::vector<std::string> masks, codes, sections, flatnet;  // comma lists
};

const FlagTable<MaskReportSettings>& mask_report_flags() {
  using S = MaskReportSettings;
  static const FlagTable<S> rows = {
      {"masks", comma_list<S, &S::masks>(), "folders written by `flatnet mask train` (comma-separated)"},
      {"images", static_cast<std::filesystem::path S::*>(&MaskReportOptions::images),
       "photographs; the held-out split (as training's and simulate's) is used"},
      {"out", static_cast<std::filesystem::path S::*>(&MaskReportOptions::out),
       "folder for report.md, masks.png, sweep.png, separable_sweep.png"},
      {"codes", comma_list<S, &S::codes>(),
       "separable code pairs NAME=codes.mat (comma-separated; 'none': no separable section). Default: MLS, the "
       "shipped separable-learned codes and their binary variant; rank-1 --masks are added as sign(u), sign(v)"},
      {"sections", comma_list<S, &S::sections>(), "wiener, separable, or both (comma-separated; default: both)"},
      {"flatnet", comma_list<S, &S::flatnet>(),
       "FlatNet models trained on a code pair's camera, NAME=model.flatnet (NAME as in --codes)"},
      {"noise", static_cast<double S::*>(&MaskReportOptions::noise), "Wiener protocol: noise sigma of the main table",
       1e-12, 1, "a positive sigma up to 1"},
      {"tune-count", static_cast<int64_t S::*>(&MaskReportOptions::tune_count),
       "held-out photographs that tune gamma and lambda", 1, 1e12, "at least 1"},
      {"count", static_cast<int64_t S::*>(&MaskReportOptions::count),
       "held-out photographs scored after those (0: the rest)", 0, 1e12, "0 (the rest) or more"},
  };
  return rows;
}

int mask_report(int argc, char** argv) {
  cxxopts::Options o(
      "flatnet mask report",
      "Compare masks: the Wiener protocol (learned masks, MLS, 02; noise sweep), then code pairs built into the "
      "separable reference camera (Tikhonov and FlatNet on held-out captures; light sweep).");
  add_flags(o, mask_report_flags());
  add_force_folder(o);
  add_common(o);
  add_precision(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("images") && r.count("out"), "mask report", "--images and --out are required");
  MaskReportSettings settings;
  read_flags(r, mask_report_flags(), settings);
  MaskReportOptions opt = settings;
  const auto claim = claim_out(r, opt.out, "mask report");
  bool separable = false;
  opt.wiener = false;
  const auto sections = r.count("sections") ? settings.sections : std::vector<std::string>{"wiener", "separable"};
  for (const auto& section : sections) {
    require(section == "wiener" || section == "separable", "--sections",
            "takes wiener and/or separable, got '" + section + "'");
    (section == "wiener" ? opt.wiener : separable) = true;
  }
  if (r.count("masks"))
    for (const auto& d : settings.masks) opt.mask_dirs.emplace_back(d);

  std::vector<std::pair<std::string, std::string>> codes = {
      {"MLS", shipped("models/camera/codes_mls.mat").string()},
      {"separable-learned", shipped("models/masks/separable/codes.mat").string()},
      {"separable-learned binary", shipped("models/masks/separable/binary/codes.mat").string()}};
  const bool no_codes = r.count("codes") && settings.codes == std::vector<std::string>{"none"};
  if (r.count("codes") && !no_codes) codes = named_paths(settings.codes, "--codes");
  if (separable && !no_codes) {
    for (const auto& [name, path] : codes) {
      for (const auto& c : opt.separable) require(c.name != name, "--codes", "names '" + name + "' twice");
      opt.separable.push_back({name, load_code_pair(path), shown(path), std::nullopt});
    }
    for (const auto& dir : opt.mask_dirs) {
      MatReader vectors(dir / "vectors.mat");
      if (vectors.read("U").size(1) != 1) continue;  // only rank-1 masks have a separable counterpart
      const auto mapped = codes_from_wiener_mask(dir);
      opt.separable.push_back({"Wiener " + dir.filename().string(), mapped.codes,
                               "sign of the Wiener-learned vectors in " + shown(dir / "vectors.mat") +
                                   " (the mask agrees on " + fixed(100 * mapped.agreement, 1) +
                                   " % of the window's pixels)",
                               std::nullopt});
    }
  }
  if (r.count("flatnet")) {
    require(!opt.separable.empty(), "--flatnet",
            "needs code pairs (--codes is none, or --sections leaves out separable)");
    const auto precision = precision_from(r);
    for (const auto& [name, path] : named_paths(settings.flatnet, "--flatnet")) {
      auto it = std::find_if(opt.separable.begin(), opt.separable.end(), [&](const auto& c) { return c.name == name; });
      require(it != opt.separable.end(), "--flatnet", "'" + name + "' names no code pair (--codes names them)");
      auto model = load_model_file(path);
      InferenceLevers levers;
      levers.bf16 = precision == Precision::bf16;
      model.generator->prepare_inference(levers);
      auto generator = model.generator;
      // The steps it trained (files from before 2026-11-24 record only the configured count,
      // which a run with a time budget never reaches).
      const auto steps = model.provenance.trained_steps.empty()
                             ? model.recorded(train_key(&TrainOptions::iterations)) + " steps configured"
                             : model.provenance.trained_steps + " steps";
      it->flatnet = CameraModel{[generator](const torch::Tensor& planes) mutable { return generator->forward(planes); },
                                model.camera.raw, shown(path) + " (" + steps + ")"};
    }
  }
  opt.separable_options.geometry = load_camera_config(default_camera_path()).raw;
  opt.separable_options.geometry.centring = Centring::plane;
  opt.separable_options.tune_count = opt.tune_count;
  opt.separable_options.count = opt.count;
  std::cout << write_mask_report(opt);
  return 0;
}

// flatnet mask separable: learns the code pair of the separable camera through Tikhonov. Configured
// like the other trainers: configs/separable_defaults.yaml, then --config, then the shortcut flags
// (each one a key), then --set.
int mask_separable(int argc, char** argv) {
  cxxopts::Options o("flatnet mask separable",
                     "Learn a separable FlatCam's codes end to end: codes -> PhiL/PhiR -> noisy capture -> Tikhonov. "
                     "Settings: configs/separable_defaults.yaml (each shortcut flag sets one of its keys).");
  add_flags(o, trainer_run_flags());
  add_row_flags(o, separable_train_fields(), setting_docs(separable_defaults()));
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("out"), "mask separable", "--out DIR is required");
  TrainerRun run;
  read_flags(r, trainer_run_flags(), run);
  auto sets = row_flag_settings(r, separable_train_fields());
  for (const auto& s : run.set) sets.push_back(s);
  const auto& out = run.out;
  const bool resume = run.resume;
  const auto c = run_config(run, sets, separable_defaults(), "code-pair training run");
  require(resume || run.force || !std::filesystem::exists(out / "codes.mat"), out,
          "already holds learned codes; choose another --out (or --force)");
  SeparableTrainOptions opt;
  read_options(c, separable_train_fields(), opt);
  const auto init = c.str(codes_init_key());
  // Named before --out is claimed, so a typo leaves no config.yaml or lock files behind.
  require_option(opt.init_codes.empty() || std::filesystem::is_regular_file(opt.init_codes), codes_init_key(),
                 "mls, random, or a codes .mat file; '" + printable(init) + "' is none of these");
  const auto& rows = separable_train_fields();
  require(opt.lr > 0, key_of(rows, &SeparableTrainOptions::lr), "must be positive for the code pair");
  require(opt.val_count >= 1, key_of(rows, &SeparableTrainOptions::val_count),
          "at least 1 (the code pair's validation needs photographs)");
  opt.out = out;
  opt.resume = resume;
  opt.force = run.force;
  const auto claim = claim_out(r, opt.out, "mask separable");
  write_text_atomically(opt.out / "config.yaml", c.to_yaml());
  watch_interrupts();
  const auto s = train_separable_codes(opt);
  std::cout << "separable codes: " << s.steps << " steps in " << format_duration(s.seconds) << "; validation PSNR "
            << s.val_psnr_start << " -> " << s.val_psnr << " dB (Tikhonov, linear light), lambda " << s.lambda
            << ", throughput " << s.throughput << "; wrote " << (opt.out / "codes.mat").string() << "\n";
  if (interrupted())
    std::cerr << "interrupted: continue with `flatnet mask separable --out " << opt.out.string() << " --resume`\n";
  return interrupted() ? 130 : 0;
}

// The settings of `flatnet mask camera`.
struct MaskCameraSettings {
  std::filesystem::path codes, out;
  uint64_t random_codes = 0;
  double calib_error = 0.03;
  uint64_t seed = 0;
  std::string centring = "plane";
  bool force = false;
};

const FlagTable<MaskCameraSettings>& mask_camera_flags() {
  using S = MaskCameraSettings;
  static const FlagTable<S> rows = {
      {"codes", &S::codes,
       ".mat with code_rows and code_cols (vectors, values in [-1, 1]); models/camera/codes_mls.mat is MLS"},
      {"random-codes", &S::random_codes,
       "instead of --codes: a seeded pair of random +-1 codes, 511 each (another FlatCam, for adaptation tests); "
       "written to OUT/codes.mat"},
      {"out", &S::out, "folder to write"},
      {"calib-error", &S::calib_error, "relative (Frobenius) error of the calibration, as a real one has", 0, 1,
       "0 to 1 (0.03: 3 %)"},
      {"seed", &S::seed, "seed of that error"},
      {"centring", &S::centring, "plane, or level (for models that read the light level, as the shipped ones)"},
      {"force", &S::force, "replace the files of an existing camera in --out"},
  };
  return rows;
}

// flatnet mask camera: the reference camera with another separable code pair.
int mask_camera(int argc, char** argv) {
  cxxopts::Options o(
      "flatnet mask camera",
      "Build the reference camera with a separable code pair: rig.mat, calib.mat (with estimation error) "
      "and camera.yaml, for simulate, calibrate, recon and train.");
  add_flags(o, mask_camera_flags());
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("codes") + r.count("random-codes") == 1 && r.count("out"), "mask camera",
          "one of --codes FILE or --random-codes SEED, and --out DIR, are required");
  MaskCameraSettings set;
  read_flags(r, mask_camera_flags(), set);
  const auto& out = set.out;
  const auto codes_path = r.count("codes") ? set.codes : out / "codes.mat";
  const double error = set.calib_error;
  CodePair codes;
  if (r.count("codes")) {
    codes = load_code_pair(codes_path);
  } else {  // +-1 with probability 1/2 each, rows then columns from one seeded generator
    auto gen = at::detail::createCPUGenerator(set.random_codes);
    codes.rows = at::randint(0, 2, {511}, gen, torch::kFloat64) * 2 - 1;
    codes.cols = at::randint(0, 2, {511}, gen, torch::kFloat64) * 2 - 1;
  }
  const auto& u = codes.rows;
  const auto& v = codes.cols;
  const auto claim = claim_out(r, out, "mask camera");
  for (const char* f : {"rig.mat", "calib.mat", "camera.yaml"}) require_new_output(out / f, set.force, {codes_path});
  if (r.count("random-codes")) write_mat(codes_path, {{"code_rows", codes.rows}, {"code_cols", codes.cols}});
  auto camera = load_camera_config(default_camera_path());
  camera.raw.centring = parse_centring(set.centring, "--centring");
  write_code_pair_camera(out, codes, camera, error, set.seed,
                         "The reference camera with the codes of " + codes_path.string() + " (`flatnet mask camera`)");
  std::cout << "camera with codes " << codes_path.string() << " (" << u.numel() << " x " << v.numel()
            << " features, mean "
            << "transmittance " << codes.throughput() << "): " << (out / "camera.yaml").string()
            << ", rig.mat, calib.mat (" << error * 100 << " % error)\n";
  return 0;
}

}  // namespace

CommandFlags mask_train_command_flags() { return command_flags("mask train", trainer_run_flags()); }
CommandFlags mask_separable_command_flags() { return command_flags("mask separable", trainer_run_flags()); }
CommandFlags mask_eval_command_flags() { return command_flags("mask eval", mask_eval_flags()); }
CommandFlags mask_report_command_flags() { return command_flags("mask report", mask_report_flags()); }
CommandFlags mask_camera_command_flags() { return command_flags("mask camera", mask_camera_flags()); }

int mask(int argc, char** argv) {
  const std::string usage =
      "usage: flatnet mask train|eval|report|camera|separable [options]  ('flatnet mask <sub> --help' lists them)";
  if (argc < 2) throw Error(usage);
  const std::string sub = argv[1];
  if (sub == "train") return mask_train(argc - 1, argv + 1);
  if (sub == "eval") return mask_eval(argc - 1, argv + 1);
  if (sub == "report") return mask_report(argc - 1, argv + 1);
  if (sub == "camera") return mask_camera(argc - 1, argv + 1);
  if (sub == "separable") return mask_separable(argc - 1, argv + 1);
  if (sub == "-h" || sub == "--help") {
    std::cout << usage << "\n";
    return 0;
  }
  throw Error("mask: unknown subcommand '" + sub + "'; " + usage);
}

}  // namespace flatnet::cli
