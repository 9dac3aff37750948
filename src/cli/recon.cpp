#include <iostream>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "core/util.hpp"
#include "eval/inversion_report.hpp"
#include "eval/niqe.hpp"
#include "core/precision.hpp"
#include "eval/report.hpp"
#include "eval/thesis_report.hpp"
#include "optics/simulator.hpp"
#include "recon/batch.hpp"
#include "recon/methods.hpp"

namespace flatnet::cli {

const FlagTable<ReconstructorSpec>& recon_method_flags() {
  using S = ReconstructorSpec;
  static const std::string methods = method_names(MethodInput::calibration);  // the registry's (recon/methods.hpp)
  static const FlagTable<S> rows = {
      {"method", &S::method, methods.c_str()},
      {"lambda", &S::lambda, "regularisation weight (0: the camera file's)", 1e-12, 1e6,
       "a positive regulariser (leave it out for the camera file's)"},
  };
  return rows;
}

const FlagTable<BatchOptions>& batch_flags() {
  using S = BatchOptions;
  static const FlagTable<S> rows = {
      {"batch", &S::batch, "captures per batch", 1, 4096, "1 to 4096 per batch"},
      {"require-fit", &S::require_fit,
       "refuse (exit 2) when a capture does not fit the camera (the model's, or the calibration's; "
       "OUT/camera_fit.csv)"},
  };
  return rows;
}

namespace {

struct ReconFiles {
  std::filesystem::path camera, calib, input, out;
};

const FlagTable<ReconFiles>& recon_file_flags() {
  static const FlagTable<ReconFiles> rows = {
      {"camera", &ReconFiles::camera, "camera .yaml (default: the reference camera)"},
      {"calib", &ReconFiles::calib, "calibration .mat (default: the camera's)"},
      {"input", &ReconFiles::input, "raw capture PNG or folder of them"},
      {"out", &ReconFiles::out, "output folder"},
  };
  return rows;
}

}  // namespace

int recon(int argc, char** argv) {
  cxxopts::Options o("flatnet recon", "Reconstruct raw captures with a classical method.");
  add_flags(o, recon_file_flags());
  add_flags(o, recon_method_flags());
  add_flags(o, batch_flags());
  add_force_folder(o);
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("input") && r.count("out"), "recon", "--input DIR|FILE and --out DIR are required");
  ReconFiles files;
  read_flags(r, recon_file_flags(), files);
  ReconstructorSpec spec;
  read_flags(r, recon_method_flags(), spec);
  // recon is the classical command: flatnet models go through infer
  require_method(spec.method, MethodInput::calibration, "recon.method");
  spec.camera = camera_from(r);
  if (r.count("calib")) spec.calibration = files.calib;
  BatchOptions opt;
  read_flags(r, batch_flags(), opt);
  opt.out = files.out;
  opt.label = spec.method;
  const auto captures = collect_captures(files.input);
  check_output_names(captures, opt.out);                         // before the calibration's SVDs
  if (!captures.empty()) spec.first_capture = captures.front();  // read once more, before the build
  auto built = make_reconstructor(spec);
  opt.fit = built.fit.get();
  require(!opt.require_fit || opt.fit, "--require-fit", "cannot judge the captures: " + built.no_fit);
  const auto claim = claim_out(r, opt.out, "recon");
  const auto rep = reconstruct_files(*built.engine, built.camera, captures, opt);
  std::cout << spec.method << ": " << rep.count << " captures -> " << opt.out.string() << " (" << rep.ms_per_capture
            << " ms per capture reconstruction, " << rep.seconds << " s in all)\n";
  if (built.fit && rep.misfits > 0) std::cerr << "warning: " << camera_fit_warning(rep, *built.fit) << "\n";
  if (built.fit && rep.unjudged > 0) std::cerr << "note: " << camera_fit_note(rep) << "\n";
  return 0;
}

namespace {

// The settings of `flatnet eval fit-niqe` (the photographs' split is simulate's).
struct FitNiqeSettings {
  std::filesystem::path images, out;
  int64_t patch = 48;
  int64_t size = 256;
  double val_fraction = SimulateOptions{}.val_fraction;
  uint64_t split_seed = 1;
  int64_t limit = 0;
  bool force = false;
};

const FlagTable<FitNiqeSettings>& fit_niqe_flags() {
  using S = FitNiqeSettings;
  static const FlagTable<S> rows = {
      {"images", &S::images, "folder of photographs"},
      {"out", &S::out, "model file to write (.mat)"},
      {"patch", &S::patch, "patch side in pixels at full scale (the paper: 96; flatnet's 256-pixel images: 48)"},
      {"size", &S::size, "scene side the photographs are shown at", 16, 8192, "16 to 8192 pixels"},
      {"val-fraction", &S::val_fraction,
       "photographs held out (as simulate's split with --split-seed): never fitted on", 0, 1, "0 to 1"},
      {"split-seed", &S::split_seed, "seed of that split"},
      {"limit", &S::limit, "fit on the first N training photographs only (0: all)", 0, 1e12, "0 (all) or more"},
      {"force", &S::force, "replace an existing --out file"},
  };
  return rows;
}

std::filesystem::path shipped_niqe() { return data_dir() / "models" / "niqe.mat"; }

// eval's and report's --niqe: a model file, or none.
void set_niqe_model(const cxxopts::ParseResult& r, const std::string& niqe, std::filesystem::path& model) {
  if (r.count("niqe")) {
    if (niqe != "none") model = niqe;
  } else if (std::filesystem::exists(shipped_niqe())) {
    model = shipped_niqe();
  }
}

// flatnet eval fit-niqe: the NIQE model of pristine photographs, as a display shows them (the
// scenes the reconstructions are compared with), from the training side of simulate's split.
int fit_niqe_command(int argc, char** argv) {
  cxxopts::Options o("flatnet eval fit-niqe", "Fit NIQE's pristine model on photographs (models/niqe.mat).");
  add_flags(o, fit_niqe_flags());
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("images") && r.count("out"), "eval fit-niqe", "--images DIR and --out FILE are required");
  FitNiqeSettings set;
  read_flags(r, fit_niqe_flags(), set);
  const auto& out = set.out;
  require_new_output(out, set.force, {});
  const auto patch = set.patch, size = set.size;
  require(patch >= 8 && patch % 2 == 0 && patch <= size, "--patch", "an even size from 8 to --size");
  auto train = split_image_files(set.images, set.val_fraction, set.split_seed).first;
  if (set.limit > 0 && static_cast<int64_t>(train.size()) > set.limit) train.resize(set.limit);
  const auto model = fit_niqe(
      train, [&](const std::filesystem::path& p) { return display_scene(p, size); }, patch);
  save_niqe(out, model);
  std::cout << "fitted NIQE on " << model.patches << " sharp " << patch << "-pixel patches of " << model.images
            << " photographs shown at " << size << "x" << size << "; wrote " << out.string() << "\n";
  return 0;
}

}  // namespace

// eval's settings: the library's options with the NIQE model as given.
struct EvalSettings : EvalOptions {
  std::string niqe;  // a .mat, or none; absent: the shipped model
};

const FlagTable<EvalSettings>& eval_flags() {
  using S = EvalSettings;
  static const FlagTable<S> rows = {
      {"gt", static_cast<std::filesystem::path S::*>(&EvalOptions::gt), "ground-truth folder"},
      {"out", static_cast<std::filesystem::path S::*>(&EvalOptions::out),
       "reconstructions: a folder of PNGs, or of one subfolder per method; reports are written here"},
      {"niqe", &S::niqe,
       "NIQE model (.mat from `flatnet eval fit-niqe`), or none (default: the shipped models/niqe.mat)"},
      {"sheet-rows", static_cast<int S::*>(&EvalOptions::sheet_rows), "images in the contact sheet", 1, 1000,
       "1 to 1000"},
  };
  return rows;
}

int eval(int argc, char** argv) {
  if (argc > 1 && std::string(argv[1]) == "fit-niqe") return fit_niqe_command(argc - 1, argv + 1);
  cxxopts::Options o("flatnet eval",
                     "PSNR, SSIM, NIQE, colour and detail kept (and LPIPS with --lpips) of reconstructions against "
                     "ground truth ('flatnet eval fit-niqe' fits NIQE's model).");
  add_flags(o, eval_flags());
  add_lpips(o);
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("gt") && r.count("out"), "eval", "--gt DIR and --out DIR are required");
  EvalSettings settings;
  read_flags(r, eval_flags(), settings);
  EvalOptions opt = settings;
  set_niqe_model(r, settings.niqe, opt.niqe_model);
  std::tie(opt.lpips, opt.lpips_files) = lpips_from(r);
  const auto scores = evaluate(opt);
  if (!opt.niqe_model.empty())
    std::cout << "NIQE (lower is more natural; model " << opt.niqe_model.string()
              << "): Ma et al.'s score needs regression forests not available here, so no perceptual index PI\n";
  std::cout << format_table(scores) << "wrote " << (opt.out / "metrics.csv").string() << " and "
            << (opt.out / "sheet.png").string() << "\n";
  return 0;
}

namespace {

struct InversionReportFiles {
  std::vector<std::string> models;  // NAME=MODEL or MODEL
  std::filesystem::path out, camera;
};

const FlagTable<InversionReportFiles>& inversion_report_flags() {
  using S = InversionReportFiles;
  static const FlagTable<S> rows = {
      {"models", comma_list<S, &S::models>(), "NAME=MODEL.flatnet or MODEL.flatnet, comma-separated"},
      {"out", &S::out, "folder for inversion.md and inversion.png"},
      {"camera", &S::camera,
       "the camera the models were trained for, whose calibration gives PhiL and PhiR (default: the reference "
       "camera)"},
  };
  return rows;
}

// flatnet report inversion: the thesis's Figure 3.3 for any model files.
int inversion_report_command(int argc, char** argv) {
  cxxopts::Options o("flatnet report inversion",
                     "What a model's inversion learned (the thesis's Figure 3.3): W1^T PhiL and W2^T PhiR before and "
                     "after training, as images and diagonal energy shares.");
  add_flags(o, inversion_report_flags());
  add_force_folder(o);
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("models") && r.count("out"), "report inversion",
          "--models NAME=M.flatnet,... and --out DIR are required");
  InversionReportFiles files;
  read_flags(r, inversion_report_flags(), files);
  InversionReportOptions opt;
  opt.out = files.out;
  const auto camera = camera_from(r);
  require(!camera.calibration.empty(), "--camera", "this camera names no calibration: the products need PhiL and PhiR");
  opt.calibration = camera.calibration;
  for (const auto& [name, file] : named_paths(files.models, "--models", true)) {
    require_regular_file(file);
    opt.models.push_back({name, file});
  }
  const auto claim = claim_out(r, opt.out, "report inversion");
  std::cout << write_inversion_report(opt) << "wrote " << (opt.out / "inversion.md").string() << " and "
            << (opt.out / "inversion.png").string() << "\n";
  return 0;
}

}  // namespace

struct ReportFiles {
  std::vector<std::string> sets, methods;  // comma lists
  std::filesystem::path camera, out;
  std::string niqe;  // a .mat, or none; absent: the shipped model
};

const FlagTable<ReportFiles>& report_file_flags() {
  using S = ReportFiles;
  // The registry's methods, named once (a row's text lives as long as the table).
  static const std::string methods_doc = method_names(MethodInput::calibration, ", ") +
                                         ", and NAME=MODEL.flatnet (default: tikhonov, tv and the two shipped models)";
  static const FlagTable<S> rows = {
      {"sets", comma_list<S, &S::sets>(),
       "evaluation sets, NAME=DIR or DIR (folders from `flatnet simulate --only val`; scripts/make_eval_sets.sh)"},
      {"methods", comma_list<S, &S::methods>(), methods_doc.c_str()},
      {"camera", &S::camera, "camera .yaml for Tikhonov and TV (default: the reference camera)"},
      {"out", &S::out, "report folder (report.md, figures, reconstructions)"},
      {"niqe", &S::niqe, "NIQE model, or none (default: models/niqe.mat)"},
  };
  return rows;
}

const FlagTable<ReportOptions>& report_flags() {
  static const FlagTable<ReportOptions> rows = {
      {"tv-count", &ReportOptions::tv_count,
       "TV on the first N captures of each set (0: all; FISTA takes seconds per capture)", 0, 1e12, "0 (all) or more"},
      {"rows", &ReportOptions::figure_rows, "scenes per figure", 1, 1000, "1 to 1000"},
  };
  return rows;
}

int report(int argc, char** argv) {
  if (argc > 1 && std::string(argv[1]) == "inversion") return inversion_report_command(argc - 1, argv + 1);
  cxxopts::Options o(
      "flatnet report",
      "The thesis's comparison as one command: every method on every held-out set, scored (PSNR, SSIM, NIQE), "
      "timed and shown; resumes from the reconstructions already in --out.");
  add_flags(o, report_file_flags());
  add_flags(o, report_flags());
  add_lpips(o);
  add_precision(o);
  add_force_folder(o);
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("sets") && r.count("out"), "report", "--sets NAME=DIR,... and --out DIR are required");
  ReportFiles files;
  read_flags(r, report_file_flags(), files);
  ReportOptions opt;
  read_flags(r, report_flags(), opt);
  opt.camera = camera_from(r);
  opt.out = files.out;
  const auto claim = claim_out(r, opt.out, "report");
  const auto models = data_dir() / "models";
  const std::vector<std::string> default_methods = {
      "tikhonov", "tv", "flatnet-transpose=" + (models / "flatnet-sim-transpose.flatnet").string(),
      "flatnet-calibfree=" + (models / "flatnet-sim-calibfree.flatnet").string()};
  for (const auto& m : r.count("methods") ? files.methods : default_methods)
    opt.methods.push_back(parse_report_method(m));
  for (const auto& s : files.sets) opt.sets.push_back(parse_report_set(s));
  set_niqe_model(r, files.niqe, opt.niqe_model);
  std::tie(opt.lpips, opt.lpips_files) = lpips_from(r);
  const auto precision = precision_from(r);
  opt.levers.bf16 = precision == Precision::bf16;
  opt.machine = cpu_features().summary() + ", " + std::to_string(at::get_num_threads()) + " threads, models in " +
                describe_precision(precision);
  opt.command = "flatnet report";
  for (int i = 1; i < argc; ++i) opt.command += std::string(" ") + argv[i];
  std::cout << make_report(opt) << "wrote " << (opt.out / "report.md").string() << "\n";
  return 0;
}

CommandFlags recon_command_flags() {
  return command_flags("recon", recon_file_flags(), recon_method_flags(), batch_flags());
}
CommandFlags eval_command_flags() { return command_flags("eval", eval_flags()); }
CommandFlags fit_niqe_command_flags() { return command_flags("eval fit-niqe", fit_niqe_flags()); }
CommandFlags report_command_flags() { return command_flags("report", report_file_flags(), report_flags()); }
CommandFlags report_inversion_command_flags() { return command_flags("report inversion", inversion_report_flags()); }

}  // namespace flatnet::cli
