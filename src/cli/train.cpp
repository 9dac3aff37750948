// flatnet train / export / import / infer: the FlatNet reconstruction network's commands.
#include <cmath>
#include <iostream>
#include <sstream>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "core/precision.hpp"
#include "core/util.hpp"
#include "io/dataset.hpp"
#include "optics/simulator.hpp"
#include "nn/checkpoint.hpp"
#include "nn/model_file.hpp"
#include "nn/onnx_export.hpp"
#include "train/options.hpp"
#include "recon/batch.hpp"
#include "recon/data_consistency.hpp"
#include "train/distributed.hpp"
#include "train/experiment.hpp"

namespace flatnet::cli {

namespace {

// Given flags override torchrun's environment (distributed_from_env), which overrides these defaults.
const FlagTable<DistributedOptions>& distributed_flags() {
  using S = DistributedOptions;
  static const FlagTable<S> rows = {
      {"world-size", &S::world_size, "processes in the job", 1, 65536, "1 to 65536"},
      {"rank", &S::rank, "this process, 0..world-size-1", 0, 65535, "0 to world-size - 1"},
      {"master-addr", &S::master_addr, "host of rank 0 (rendezvous)"},
      {"master-port", &S::master_port, "TCP port of the rendezvous on rank 0", 1, 65535, "a TCP port"},
      {"dist-timeout", &S::timeout_s, "seconds a collective may wait before the job fails"},
  };
  return rows;
}

// flatnet train's own flags (the config's rows are train/options.cpp's).
struct TrainSettings {
  std::filesystem::path config, out, init_from, source_camera;
  std::vector<std::string> set;  // --set key=value, repeatable, in order
  bool resume = false, force = false;
  std::string reinit;
};

const FlagTable<TrainSettings>& train_command_rows() {
  using S = TrainSettings;
  static const FlagTable<S> rows = {
      {"config", &S::config, "experiment config (configs/*.yaml); defaults.yaml alone when absent"},
      {"set", &S::set, "override a setting: --set train.iterations=100 (repeatable)"},
      {"out", &S::out, "run folder (checkpoints, logs, model.flatnet)"},
      {"resume", &S::resume, "continue the run in --out from its latest checkpoint"},
      {"force", &S::force,
       "start afresh in an --out folder that holds another run (its checkpoints and logs are deleted)"},
      {"init-from", &S::init_from,
       "start from a model file's generator weights (a shipped model, or one from another camera's run) with fresh "
       "optimisers; the config must describe the same architecture"},
      {"source-camera", &S::source_camera,
       "with --reinit inversion and model.inversion.init transfer: the camera .yaml the --init-from model was "
       "trained for (default: the model's data.camera)"},
      {"reinit", &S::reinit,
       "with --init-from: 'inversion' keeps the model's enhancer (and level path) and initialises the first stage "
       "afresh for this run's camera, from its calibration or geometry (model.inversion.init): adapting a model to "
       "another camera"},
  };
  return rows;
}

// --data-consistency model|off|C and --consistency-blur model|S: the model's own unless given.
constexpr const char* kModelsOwnText = "model";
double model_or_number(const std::string& text, const NumberRule& rule) {
  if (text == kModelsOwnText) return ReconstructorSpec::kModelsOwn;
  const auto problem = number_problem(text, rule);
  if (!problem.empty()) throw std::invalid_argument(problem + ": " + rule.meaning);
  return std::strtod(text.c_str(), nullptr);  // std::stod throws on a subnormal (1e-320)
}
std::string model_or_number_text(double value) {
  if (value == ReconstructorSpec::kModelsOwn) return kModelsOwnText;
  std::ostringstream s;
  s << value;
  return s.str();
}
void set_consistency_strength(ReconstructorSpec& s, const std::string& text) {
  s.data_consistency =
      text == "off" ? 0 : model_or_number(text, {"data-consistency", 0, 1e3, "model, off, or a strength in (0, 1000]"});
}
std::string consistency_strength_text(const ReconstructorSpec& s) {
  return s.data_consistency == 0 ? "off" : model_or_number_text(s.data_consistency);
}
void set_consistency_blur(ReconstructorSpec& s, const std::string& text) {
  s.consistency_blur = model_or_number(text, {"consistency-blur", 0, 64, "model, or 0 (none) to 64 scene pixels"});
}
std::string consistency_blur_text(const ReconstructorSpec& s) { return model_or_number_text(s.consistency_blur); }

}  // namespace

int train(int argc, char** argv) {
  cxxopts::Options o("flatnet train", "Train a FlatNet reconstruction network (GAN, FlatNet-sep).");
  add_flags(o, train_command_rows());
  add_row_flags(o, train_fields(), setting_docs(Config::default_path()));  // --iterations, --lr, --seed ...
  add_flags(o, distributed_flags(), "distributed (defaults: torchrun's WORLD_SIZE, RANK, MASTER_ADDR, MASTER_PORT)");
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("out"), "train", "--out DIR is required");
  TrainSettings settings;
  read_flags(r, train_command_rows(), settings);
  ExperimentOptions e;
  e.out = settings.out;
  e.force = settings.force;
  e.config = settings.config;
  e.sets = row_flag_settings(r, train_fields());
  for (const auto& s : settings.set) e.sets.push_back(s);  // --set last: it wins, as in `mask separable`
  e.resume = settings.resume;
  e.init_from = settings.init_from;
  if (r.count("reinit")) {
    require(settings.reinit == "inversion", "--reinit",
            "'" + printable(settings.reinit) +
                "': only 'inversion' (the camera-specific first stage) can be "
                "re-initialised");
    require(r.count("init-from") > 0, "--reinit", "needs --init-from MODEL");
    e.reinit_inversion = true;
  }
  e.source_camera = settings.source_camera;
  auto& dist = e.distributed;
  dist = distributed_from_env();
  read_flags(r, distributed_flags(), dist);
  require(dist.rank < dist.world_size, "--rank",
          std::to_string(dist.rank) + " is outside [0, world size " + std::to_string(dist.world_size) + ")");
  // Rank 0 writes the run folder: it claims it (one run at a time; never a folder of other output).
  // A --resume with nothing to resume is refused before the folder is touched.
  OutputClaim claim;
  if (dist.rank == 0) {
    if (e.resume)
      require(std::filesystem::exists(e.out / "latest.ckpt"), e.out / "latest.ckpt",
              "nothing to resume (no checkpoint)");
    claim = claim_out(r, e.out, "train", "", "latest.ckpt");
  }
  watch_interrupts();
  // --threads 0 takes the cores other work leaves free (free_cores): say so when that is fewer than all.
  if (at::get_num_threads() < all_cores())
    std::cerr << "threads: " << at::get_num_threads() << " of " << all_cores()
              << " cores (--threads sets it; by default, the cores that other work leaves free)\n";
  const auto result = run_experiment(e);
  const auto& s = result.summary;
  if (!result.writer) {
    std::cout << "rank " << dist.rank << ": steps " << s.first_step << ".." << s.last_step << " done\n";
    return interrupted() ? 130 : 0;
  }
  std::cout << "steps " << s.first_step << ".." << s.last_step << " in " << format_duration(s.seconds) << " ("
            << s.steps_per_s << " steps/s on " << at::get_num_threads() << " threads, data wait " << s.loader_wait_s
            << " s)\n"
            << "validation: last PSNR " << s.last_psnr << " SSIM " << s.last_ssim << ", best PSNR " << s.best_psnr
            << "\nmodel: " << (e.out / "model.flatnet").string() << "\n";
  if (s.budget_reached)
    std::cout << "stopped at the time budget (train.minutes); a larger budget continues it: `flatnet train --out "
              << e.out.string() << " --resume --minutes N`\n";
  if (interrupted()) {
    std::cout << "interrupted: continue with `flatnet train --out " << e.out.string() << " --resume`\n";
    return 130;
  }
  return 0;
}

namespace {

// flatnet export's flags.
struct ExportSettings {
  std::filesystem::path checkpoint, model, out, onnx;
  std::vector<std::string> average_of, scores;  // comma lists A,B,...
  std::string method;
  bool state_dict = false, flatnet_checkpoint = false, force = false;
  // --data-consistency and --consistency-blur, read as infer reads them; the blur 0 unless given.
  ReconstructorSpec consistency = [] {
    ReconstructorSpec spec;
    spec.consistency_blur = 0;
    return spec;
  }();
};

const FlagTable<ExportSettings>& export_flags() {
  using S = ExportSettings;
  static const FlagTable<S> rows = {
      {"checkpoint", &S::checkpoint, "training checkpoint (RUN/best.ckpt or latest.ckpt)"},
      {"model", &S::model, "model file (instead of --checkpoint; for --state-dict)"},
      {"average-of", comma_list<S, &S::average_of>(),
       "instead of --checkpoint or --model: the mean of the weights of these model files or checkpoints (A,B,...; "
       "checkpoints give their moving average), e.g. the last snapshots of one run's low-rate end; one model and "
       "camera, the last file's record"},
      {"out", &S::out, "file to write"},
      {"state-dict", &S::state_dict,
       "write torch.save(state_dict) with FlatNet-sep's parameter names instead of a model file"},
      {"flatnet-checkpoint", &S::flatnet_checkpoint,
       "write FlatNet's checkpoint layout {'gen_state_dict': state_dict} (its main.py loads it)"},
      {"onnx", &S::onnx,
       "write an ONNX graph to this file (input meas {batch,4,rows,cols}, output image {batch,3,N,N}; ONNX Runtime "
       "and OpenCV DNN read it: `flatnet infer --engine opencv`)"},
      {"scores", comma_list<S, &S::scores>(),
       "record held-out scores in the model file: SET=EVAL_DIR,... (folders `flatnet eval` wrote, or their "
       "scores.json); `flatnet info` prints them"},
      {"method", &S::method, "with --scores: which method of the eval folder is this model (default: its only one)"},
      {"data-consistency",
       FlagText<S>{[](S& s, const std::string& text) { set_consistency_strength(s.consistency, text); },
                   [](const S& s) { return consistency_strength_text(s.consistency); }},
       "with --out: the data-consistency step the model applies at inference unless `infer --data-consistency` says "
       "otherwise (its strength C, 0 or off: none; docs/evaluation.md), kept in the file's model spec (model: the "
       "file's own, unchanged)"},
      {"consistency-blur",
       FlagText<S>{[](S& s, const std::string& text) { set_consistency_blur(s.consistency, text); },
                   [](const S& s) { return consistency_blur_text(s.consistency); }},
       "with --data-consistency: the correction's blur (scene pixels)"},
      {"force", &S::force, "replace an existing --out file"},
  };
  return rows;
}

// `export --data-consistency C --consistency-blur B`: the step the model file applies at inference by
// default (ReconstructorSpec::kModelsOwn). A model trained without the step keeps its weights; its
// provenance says the step was set at export, not trained with.
void set_inference_consistency(const cxxopts::ParseResult& r, const ReconstructorSpec& given, ModelFile& m) {
  require(r.count("out") && !(r.count("state-dict") || r.count("flatnet-checkpoint")), "--data-consistency",
          "is kept in a model file (--out), not in ONNX or state-dict exports");
  require(r.count("data-consistency") > 0, "--consistency-blur", "needs --data-consistency");
  // Read as `infer` reads the same flags; "model" (the file's own) has no meaning when writing one.
  require(given.data_consistency != ReconstructorSpec::kModelsOwn, "--data-consistency",
          "takes off or a number when writing a model file, not model");
  require(given.consistency_blur != ReconstructorSpec::kModelsOwn, "--consistency-blur",
          "takes a number when writing a model file, not model");
  require(given.consistency_blur == 0 || given.data_consistency > 0, "--consistency-blur",
          "blurs the data-consistency step's correction, and --data-consistency off writes no step: leave the blur "
          "out");
  const auto reach = consistency_blur_reach_problem(given.consistency_blur, m.camera.scene_size);
  require(reach.empty(), "--consistency-blur", reach);
  const bool trained_with = m.provenance.consistency == kConsistencyTrained;
  m.spec.consistency_strength = given.data_consistency;
  m.spec.consistency_blur = given.data_consistency > 0 ? given.consistency_blur : 0;
  std::ostringstream step;
  step << "data consistency c " << m.spec.consistency_strength << ", blur " << m.spec.consistency_blur;
  m.provenance.consistency = m.spec.consistency_strength <= 0 ? ""
                             : trained_with                   ? kConsistencyTrained
                                                              : kConsistencySetAtExport;
  if (m.spec.consistency_strength > 0 && !trained_with)
    m.provenance.source += (m.provenance.source.empty() ? "" : "; ") + step.str() + " set at export, not trained with";
  std::cerr << "the model applies "
            << (m.spec.consistency_strength > 0 ? step.str() : std::string("no data consistency"))
            << " at inference unless `infer --data-consistency` says otherwise\n";
}

}  // namespace

int export_model(int argc, char** argv) {
  cxxopts::Options o("flatnet export", "Export a trained model: a self-contained model file, or a PyTorch state_dict.");
  add_flags(o, export_flags());
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require((r.count("out") + r.count("onnx") == 1) &&
              (r.count("checkpoint") + r.count("model") + r.count("average-of") == 1),
          "export",
          "one of --checkpoint CKPT, --model MODEL or --average-of A,B,..., and one of --out FILE or --onnx FILE, are "
          "required");
  require(r.count("state-dict") + r.count("flatnet-checkpoint") + r.count("onnx") <= 1, "export",
          "give one of --state-dict, --flatnet-checkpoint and --onnx");
  ExportSettings settings;
  read_flags(r, export_flags(), settings);
  const std::filesystem::path out = r.count("onnx") ? settings.onnx : settings.out;
  std::vector<std::filesystem::path> inputs;
  if (r.count("average-of"))
    for (const auto& a : settings.average_of) {
      require(!a.empty(), "--average-of", "holds an empty name (two commas together?): list the files as A,B,...");
      inputs.emplace_back(a);
    }
  else
    inputs.emplace_back(r.count("checkpoint") ? settings.checkpoint : settings.model);
  require_new_output(out, settings.force, inputs);
  require(!r.count("scores") || !(r.count("onnx") || r.count("state-dict") || r.count("flatnet-checkpoint")),
          "--scores", "is recorded in a model file (--out), not in ONNX or state-dict exports");
  bool average = false;
  auto m = r.count("average-of")   ? average_models(inputs)
           : r.count("checkpoint") ? model_from_checkpoint(inputs[0], &average)
                                   : load_model_file(inputs[0]);
  if (r.count("average-of")) std::cerr << "averaging the weights of " << inputs.size() << " models\n";
  if (r.count("scores")) m.provenance.scores = recorded_scores(settings.scores, settings.method);
  if (average) std::cerr << "exporting the moving average of the weights (train.ema_decay)\n";
  if (r.count("data-consistency") || r.count("consistency-blur")) set_inference_consistency(r, settings.consistency, m);
  if (m.spec.consistency_strength > 0 && (r.count("onnx") || r.count("state-dict") || r.count("flatnet-checkpoint")))
    std::cerr << "warning: this model was trained with its pictures corrected by their captures (model.consistency); "
                 "the exported network does not hold that step (recon/data_consistency.hpp: apply it after the "
                 "network, through the camera's calibration)\n";
  if (r.count("onnx")) {
    const auto rep = export_onnx(out, m.generator, m.camera);
    std::cout << "wrote ONNX " << out.string() << " (" << rep.nodes << " nodes, " << rep.initializers
              << " weight tensors, " << rep.bytes / 1e6 << " MB; input meas {batch,4," << m.camera.raw.crop[2] << ","
              << m.camera.raw.crop[3] << "}, output image {batch,3," << m.camera.scene_size << ","
              << m.camera.scene_size << "}; checked by ONNX's checker)\n";
  } else if (r.count("state-dict") || r.count("flatnet-checkpoint")) {
    const bool flatnet_layout = r.count("flatnet-checkpoint") > 0;
    export_state_dict(out, m.generator,
                      flatnet_layout ? StateDictLayout::flatnet_checkpoint : StateDictLayout::state_dict);
    std::cout << "wrote " << (flatnet_layout ? "FlatNet checkpoint " : "state dict ") << out.string() << " ("
              << m.generator->named_parameters().size() << " parameters; python: "
              << (flatnet_layout ? "G.load_state_dict(torch.load(path)['gen_state_dict'])"
                                 : "model.load_state_dict(torch.load(path))")
              << ")\n";
  } else {
    save_model_file(out, m.generator, model_identity(m));
    std::cout << "wrote model " << out.string() << (r.count("scores") ? " with its scores" : "") << "\n";
  }
  return 0;
}

namespace {

struct ImportSettings {
  std::filesystem::path state_dict, config, camera, out;
  std::vector<std::string> set;  // --set key=value, repeatable
  bool verbose = false, force = false;
};

const FlagTable<ImportSettings>& import_flags() {
  using S = ImportSettings;
  static const FlagTable<S> rows = {
      {"state-dict", &S::state_dict, "torch.save'd state dict (or FlatNet checkpoint with gen_state_dict)"},
      {"config", &S::config, "config describing the architecture (e.g. configs/flatnet_paper.yaml)"},
      {"set", &S::set, "override a setting (repeatable)"},
      {"camera", &S::camera, "camera the weights were trained for (default: the config's data.camera)"},
      {"out", &S::out, "model file to write"},
      {"verbose", &S::verbose, "list the file's tensors that the model does not use"},
      {"force", &S::force, "replace an existing --out file"},
  };
  return rows;
}

}  // namespace

int import_model(int argc, char** argv) {
  cxxopts::Options o("flatnet import", "Make a model file from a PyTorch state_dict with FlatNet-sep's names.");
  add_flags(o, import_flags());
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("state-dict") && r.count("out"), "import", "--state-dict FILE and --out MODEL are required");
  ImportSettings settings;
  read_flags(r, import_flags(), settings);
  const auto& out = settings.out;
  require_new_output(out, settings.force, {settings.state_dict});
  auto config = Config::load(settings.config, settings.set);
  const auto camera = r.count("camera") ? load_camera_config(settings.camera)
                                        : load_camera_config(config.path(data_key(&DataOptions::camera)));
  Generator g(generator_options(config, camera, false));
  const auto rep = import_state_dict(settings.state_dict, g);
  save_model_file(out, g, config, camera);
  std::cout << "read " << rep.used << " tensors from " << rep.source
            << (rep.data_parallel ? " (DataParallel names)" : "") << "; " << rep.unused.size() << " unused"
            << (rep.unused.empty() || settings.verbose ? "" : " (--verbose lists them)") << "\n";
  if (r.count("verbose"))
    for (const auto& name : rep.unused) std::cout << "  unused: " << name << "\n";
  std::cout << "wrote model " << out.string() << "\n";
  return 0;
}

namespace {

// What `infer` reads and writes, and the engine it runs the model on (its settings that are not the
// reconstructor's).
struct InferSettings {
  std::filesystem::path model, input, out, camera;
  bool self_ensemble = false;
  std::string engine = "libtorch";
};

const FlagTable<InferSettings>& infer_engine_flags() {
  using S = InferSettings;
  static const FlagTable<S> rows = {
      {"model", &S::model, "model file (models/*.flatnet or RUN/model.flatnet; an .onnx file with --engine opencv)"},
      {"input", &S::input, "raw capture PNG or folder of them"},
      {"out", &S::out, "output folder (PNGs with the captures' names)"},
      {"camera", &S::camera, "camera .yaml whose preprocessing to use (default: the model's)"},
      {"self-ensemble", &S::self_ensemble,
       "average the enhancer over the image and its three flips (test-time self-ensemble; about 4x the enhancer's "
       "time; libtorch engine)"},
      {"engine", &S::engine,
       "libtorch, or opencv: an ONNX file from `flatnet export --onnx` through OpenCV's DNN module"},
  };
  return rows;
}

const FlagTable<ReconstructorSpec>& infer_flags() {
  using S = ReconstructorSpec;
  static const FlagTable<S> rows = {
      {"levers", FlagText<S>{set_levers_of<S, &S::levers>, levers_text_of<S, &S::levers>},
       "exact inference speed-ups: none, or a list of fold, channels-last, gemm-up, onednn (bf16 and onednn: see "
       "--precision)"},
      {"data-consistency", FlagText<S>{set_consistency_strength, consistency_strength_text},
       "C > 0: correct each picture by its capture where the camera measures it well (Tikhonov on the picture's "
       "residual, regulariser C^2 tikhonov_lambda; 10 for the shipped models, docs/evaluation.md); off; model: the "
       "model's own (a model trained with the step, model.consistency, applies it; others do not)"},
      {"consistency-blur", FlagText<S>{set_consistency_blur, consistency_blur_text},
       "sigma (scene pixels, 0 to 64) of a Gaussian on that correction: its coarse part alone (0: none); model: the "
       "model's own (0 for a model trained without the step)"},
  };
  return rows;
}

const FlagTable<AdaptationOptions>& adaptation_flags() {
  using S = AdaptationOptions;
  static const FlagTable<S> rows = {
      {"adapt-steps", &S::steps,
       "N > 0: first adapt the model to the captures for N Adam steps, on their disagreement with its pictures where "
       "the camera measures well and a pull to the shipped weights (docs/evaluation.md); 0: off"},
      {"adapt-lr", &S::lr, "its Adam rate"},
      {"adapt-anchor", &S::anchor, "weight of the pull to the shipped weights (relative squared distance)"},
      {"adapt-brightness", &S::brightness,
       "weight of the term that keeps each picture's brightness the shipped model's"},
      {"adapt-batch", &S::batch, "captures a step"},
      {"adapt-captures", &S::captures, "at most this many of the captures adapt the model (evenly spread)"},
  };
  return rows;
}

}  // namespace

CommandFlags train_command_flags() { return command_flags("train flags", train_command_rows(), distributed_flags()); }
CommandFlags export_command_flags() { return command_flags("export", export_flags()); }
CommandFlags import_command_flags() { return command_flags("import", import_flags()); }

CommandFlags infer_command_flags() {
  return command_flags("infer", infer_engine_flags(), infer_flags(), batch_flags(), adaptation_flags());
}

// Every flag of `flatnet infer`.
cxxopts::Options infer_options() {
  cxxopts::Options o("flatnet infer", "Reconstruct raw captures with a trained FlatNet model.");
  add_flags(o, infer_engine_flags());
  add_flags(o, infer_flags());
  add_flags(o, batch_flags());
  add_flags(o, adaptation_flags(),
            "test-time adaptation (the model fine-tuned on the captures themselves, no ground truth)");
  add_force_folder(o);
  add_precision(o);
  add_common(o);
  return o;
}

// What `infer` builds, from its flags (each checked, the flag named).
ReconstructorSpec infer_spec(const cxxopts::ParseResult& r, const InferSettings& settings) {
  const auto& engine = settings.engine;
  ReconstructorSpec spec;
  read_flags(r, infer_flags(), spec);
  read_flags(r, adaptation_flags(), spec.adapt);
  spec.method = engine == "opencv" ? "opencv" : "flatnet";
  spec.model = settings.model;
  spec.use_camera = r.count("camera") > 0;  // else the preprocessing the model file carries
  if (spec.use_camera) spec.camera = load_camera_config(settings.camera);
  if (precision_from(r) == Precision::bf16) spec.levers.bf16 = true;  // the enhancer in bf16; inversion, sigmoid fp32
  spec.levers.self_ensemble = settings.self_ensemble;
  require(!spec.levers.self_ensemble || engine == "libtorch", "--self-ensemble",
          "runs on the libtorch engine (an ONNX file holds the plain model)");
  require(spec.data_consistency <= 0 || engine == "libtorch", "--data-consistency",
          "runs on the libtorch engine (an ONNX file carries no calibration)");
  spec.adapt.bf16 = spec.levers.bf16;
  check_adaptation_options(spec.adapt);
  require(spec.adapt.steps == 0 || engine == "libtorch", "--adapt-steps",
          "runs on the libtorch engine (an ONNX file is not trained)");
  return spec;
}

// What makes one folder's reconstructions one model's: a rerun with other settings is refused.
std::string infer_settings(const ReconstructorSpec& spec) {
  std::ostringstream settings;
  settings << "model " << file_fingerprint(spec.model);
  if (spec.data_consistency != ReconstructorSpec::kModelsOwn || spec.consistency_blur != ReconstructorSpec::kModelsOwn)
    settings << " data-consistency " << spec.data_consistency << " blur " << spec.consistency_blur;
  if (spec.adapt.steps > 0)
    settings << " adapt " << spec.adapt.steps << " lr " << spec.adapt.lr << " anchor " << spec.adapt.anchor
             << " brightness " << spec.adapt.brightness << " batch " << spec.adapt.batch << " captures "
             << spec.adapt.captures;
  return settings.str();
}

int infer(int argc, char** argv) {
  auto o = infer_options();
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  require(r.count("model") && r.count("input") && r.count("out"), "infer",
          "--model MODEL, --input DIR|FILE and --out DIR are required");
  InferSettings settings;
  read_flags(r, infer_engine_flags(), settings);
  const auto& engine = settings.engine;
  require(engine == "libtorch" || engine == "opencv", "--engine",
          "libtorch or opencv expected, got '" + printable(engine) + "'");
  auto spec = infer_spec(r, settings);
  BatchOptions opt;
  read_flags(r, batch_flags(), opt);
  opt.out = settings.out;
  opt.label = "infer";
  const auto captures = collect_captures(settings.input);
  spec.adapt_on = captures;
  check_output_names(captures, opt.out);                         // never over a capture, even with --force
  if (!captures.empty()) spec.first_capture = captures.front();  // read once more, before the build
  auto built = make_reconstructor(spec);
  if (!built.warning.empty()) std::cerr << "warning: " << built.warning << "\n";
  // One folder holds one model's reconstructions: a rerun with another model is refused, not mixed.
  const auto claim = claim_out(r, opt.out, "infer", infer_settings(spec));
  if (engine == "opencv")
    std::cerr << "engine: " << built.engine->describe() << " (--levers and --precision apply to libtorch)\n";
  if (built.corrected) std::cerr << "engine: " << built.engine->describe() << "\n";
  if (!built.adaptation.empty()) std::cerr << "adaptation: " << built.adaptation << "\n";
  opt.fit = built.fit.get();
  require(!opt.require_fit || opt.fit, "--require-fit", "cannot judge the captures: " + built.no_fit);
  if (built.fit)
    std::cerr << "camera: the model is for camera '" << printable(built.fit->camera_name())
              << "'; each capture's fit to it goes to camera_fit.csv\n";
  else
    std::cerr << "camera: no camera fit (" << printable(built.no_fit) << ")\n";
  const auto rep = reconstruct_files(*built.engine, built.camera, captures, opt);
  std::cout << "flatnet: " << rep.count << " captures -> " << opt.out.string() << " (" << rep.captures_per_s
            << " images/s, " << rep.ms_per_capture << " ms per image in the network";
  if (!rep.steady_state)
    std::cout << ", set-up included: one batch)\n";
  else
    std::cout << "; the first batch, which sets it up, " << rep.first_batch_ms << " ms per image)\n";
  if (built.fit && rep.misfits > 0) std::cerr << "warning: " << camera_fit_warning(rep, *built.fit) << "\n";
  if (built.fit && rep.unjudged > 0) std::cerr << "note: " << camera_fit_note(rep) << "\n";
  return 0;
}

}  // namespace flatnet::cli
