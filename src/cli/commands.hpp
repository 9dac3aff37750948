#pragma once
// flatnet subcommands. Each parses its flags, builds library objects, calls the library, reports.
#include <cxxopts.hpp>
#include <map>
#include <string>
#include <vector>

#include "cli/flag_rows.hpp"
#include "io/camera_config.hpp"
#include "io/option_table.hpp"
#include "core/output_dir.hpp"
#include "core/precision.hpp"
#include "nn/generator.hpp"
#include "nn/lpips.hpp"

namespace flatnet {
struct SimulateOptions;    // optics/simulator.hpp
struct ReconstructorSpec;  // recon/reconstructor.hpp
struct BatchOptions;       // recon/batch.hpp
struct EvalOptions;        // eval/report.hpp
struct ReportOptions;      // eval/thesis_report.hpp
struct MaskReportOptions;  // eval/mask_report.hpp
}  // namespace flatnet

namespace flatnet::cli {

int simulate(int argc, char** argv);
// Each command's flag rows (cli/flag_rows.hpp), and all of them for `flatnet options --for`.
const FlagTable<SimulateOptions>& simulate_flags();
CommandFlags simulate_command_flags();
CommandFlags calibrate_command_flags();
CommandFlags recon_command_flags();
// --batch and --require-fit of every command that reconstructs files (recon, infer).
const FlagTable<BatchOptions>& batch_flags();
CommandFlags eval_command_flags();
CommandFlags fit_niqe_command_flags();
CommandFlags report_command_flags();
CommandFlags report_inversion_command_flags();
CommandFlags infer_command_flags();
CommandFlags train_command_flags();  // "train flags": the command line's own; the config's rows: --for train
CommandFlags export_command_flags();
CommandFlags import_command_flags();
CommandFlags mask_train_command_flags();
CommandFlags mask_separable_command_flags();
CommandFlags mask_eval_command_flags();
CommandFlags mask_report_command_flags();
CommandFlags mask_camera_command_flags();
CommandFlags bench_command_flags();
CommandFlags demo_command_flags();
CommandFlags cameras_command_flags();
CommandFlags capture_command_flags();
CommandFlags capture_dataset_command_flags();
CommandFlags capture_calibration_command_flags();
CommandFlags live_command_flags();
std::vector<CommandFlags> every_command_flags();
int calibrate(int argc, char** argv);
int recon(int argc, char** argv);
int eval(int argc, char** argv);
int report(int argc, char** argv);
int demo(int argc, char** argv);
int train(int argc, char** argv);
int export_model(int argc, char** argv);
int info(int argc, char** argv);
// Every setting of a trainer's config with its default, range and documentation.
int options(int argc, char** argv);
// --scores SET=EVAL_DIR (or SET=.../scores.json),...: one method's means per set, as the JSON a model
// file records (Provenance::scores). `method` empty: the only method the file scores.
std::string recorded_scores(const std::vector<std::string>& items, const std::string& method);
int import_model(int argc, char** argv);
int infer(int argc, char** argv);
int mask(int argc, char** argv);
int cameras(int argc, char** argv);
int capture(int argc, char** argv);
int capture_dataset(int argc, char** argv);
int capture_calibration(int argc, char** argv);
int live(int argc, char** argv);
int bench(int argc, char** argv);

// Library errors mark the options they name by key, `<options>.<field>` (`simulate.val_fraction`
// for SimulateOptions::val_fraction, `experiment.init_from`; core/error.hpp option_key): a library
// caller never passed a flag. The CLI's user knows them as flags: a key shows as the running
// command's flag named after its field (`--val-fraction`, `--init-from`) when the command has one
// (parse() records them), else as the key. main renders every Error through this.
std::string flag_or_key(const std::string& key);

// Flags from an option table: each row with a flag becomes --flag (a switch for a true/false
// setting, else a value), its help the row's key and the setting's one doc text, its comment in the
// command's defaults file (`docs`: setting_docs), so flag, key and `flatnet options` never drift apart.
template <class S>
void add_row_flags(cxxopts::Options& options, const std::vector<OptionField<S>>& fields,
                   const std::map<std::string, std::string>& docs, const std::string& prefix = "") {
  for (const auto& f : fields) {
    if (!*f.flag) continue;
    const auto key = prefix + f.key;
    const auto doc = docs.find(key);
    const auto help = key + (doc != docs.end() && !doc->second.empty() ? ": " + doc->second : std::string());
    if (std::holds_alternative<bool S::*>(f.member))
      options.add_options()(f.flag, help + " (sets it true)");
    else
      options.add_options()(f.flag, help, cxxopts::value<std::string>());
  }
}
// The given row flags as `key=value` settings, in the table's order.
template <class S>
std::vector<std::string> row_flag_settings(const cxxopts::ParseResult& r, const std::vector<OptionField<S>>& fields,
                                           const std::string& prefix = "") {
  std::vector<std::string> sets;
  for (const auto& f : fields) {
    if (!*f.flag || !r.count(f.flag)) continue;
    const bool is_switch = std::holds_alternative<bool S::*>(f.member);
    sets.push_back(prefix + f.key + "=" + (is_switch ? std::string("true") : r[f.flag].template as<std::string>()));
  }
  return sets;
}

// The --levers row's reader and writer for a struct whose member M holds the levers (infer's spec,
// bench's options): the text parse_inference_levers reads, whose errors name the flag; the
// self-ensemble, not a speed-up, keeps its own switch.
template <class S, InferenceLevers S::*M>
void set_levers_of(S& s, const std::string& text) {
  const bool self_ensemble = (s.*M).self_ensemble;
  s.*M = parse_inference_levers(text);
  (s.*M).self_ensemble = self_ensemble;
}
template <class S, InferenceLevers S::*M>
std::string levers_text_of(const S& s) {
  return inference_levers_text(s.*M);
}

// Shared flag handling.
struct CommonSettings {
  int threads = 0;  // 0: the cores other work leaves free (free_cores)
};
const FlagTable<CommonSettings>& common_flags();
void add_common(cxxopts::Options& options);  // --threads, --help
// Parses; prints help and returns false on --help. Applies --threads.
bool parse(cxxopts::Options& options, int argc, char** argv, cxxopts::ParseResult& result);
// A single output file: never one of `inputs` (even with --force), and an existing file only with --force.
void require_new_output(const std::filesystem::path& out, bool force,
                        const std::vector<std::filesystem::path>& inputs = {});
// --precision auto|fp32|bf16 (auto: bf16 where the CPU runs it natively).
struct PrecisionChoice {
  std::string precision = "auto";
};
const FlagTable<PrecisionChoice>& precision_flags();
void add_precision(cxxopts::Options& options);
// The resolved choice, printed once to stderr ("precision: bf16 (AMX)"); asks for AMX tiles when bf16.
Precision precision_from(const cxxopts::ParseResult& r);
// --camera FILE (yaml or rig .mat); the reference camera when absent.
// Claims the --out folder for `command` (core/output_dir.hpp); `--force` (when the command has it)
// writes into a folder that holds other output. Keep the claim alive while writing.
OutputClaim claim_out(const cxxopts::ParseResult& r, const std::filesystem::path& out, const std::string& command,
                      const std::string& settings = "", const std::string& own_file = "");
// "--force" for commands whose only output is a folder.
struct ForceChoice {
  bool force = false;
};
const FlagTable<ForceChoice>& force_folder_flags();
void add_force_folder(cxxopts::Options& options);

CameraConfig camera_from(const cxxopts::ParseResult& r, const std::string& flag = "camera");
// --lpips alex|vgg and --lpips-dir DIR (eval, report).
struct LpipsChoice {
  std::string backbone;             // empty: no LPIPS column
  std::filesystem::path directory;  // empty: the default search
};
const FlagTable<LpipsChoice>& lpips_flags();
void add_lpips(cxxopts::Options& options);
// The LPIPS backbone to score with and its files, or {"", {}} without --lpips. A wrong backbone name
// is an error; missing weight files are not: one line on stderr says which files to get and where
// they go, and the other metrics still run.
std::pair<std::string, LpipsFiles> lpips_from(const cxxopts::ParseResult& r);
// NAME=PATH,NAME=PATH -> pairs; errors name the flag. With `bare_allowed`, a PATH alone is named
// after its file's stem.
std::vector<std::pair<std::string, std::string>> named_paths(const std::vector<std::string>& items,
                                                             const std::string& flag, bool bare_allowed = false);

}  // namespace flatnet::cli
