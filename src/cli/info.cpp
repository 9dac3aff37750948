// flatnet info: what a model file (or checkpoint) holds, without reading the code; and the held-out
// scores `flatnet export --scores` records in a model file.
#include <cxxopts.hpp>
#include <iomanip>
#include <map>
#include <regex>
#include <iostream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "cli/commands.hpp"
#include "core/error.hpp"
#include "core/util.hpp"
#include "nn/checkpoint.hpp"
#include "nn/model_file.hpp"
#include "train/options.hpp"

namespace flatnet::cli {

namespace {

std::string join(const std::vector<std::string>& items, const std::string& separator) {
  std::string out;
  for (const auto& item : items) out += (out.empty() ? "" : separator) + item;
  return out;
}

// "1 mse + 0.2 ssim" from the recorded training config ("not recorded" without one): every loss
// weight the trainer reads (its option table), so a new term is never left out here.
std::string join_nonzero_losses(const ModelFile& m) {
  const std::string prefix = "loss.";
  std::string out;
  for (const auto& field : train_fields()) {
    const std::string key = field.key;
    if (key.rfind(prefix, 0) != 0) continue;
    const auto text = m.recorded(key);  // "" when not recorded, which is no number
    if (!is_decimal_number(text)) continue;
    const double weight = std::strtod(text.c_str(), nullptr);
    if (weight == 0) continue;
    std::ostringstream os;
    os << (out.empty() ? "" : " + ") << weight << " " << key.substr(prefix.size());
    out += os.str();
  }
  return out.empty() ? (m.recipe.empty() ? "not recorded" : "none") : out;
}

// A recorded setting (a number as C++ prints it), or "?" where the file does not record it.
std::string recorded_or_unknown(const ModelFile& m, const std::string& key) {
  const auto value = m.recorded(key);
  if (value.empty()) return "?";
  if (!is_decimal_number(value)) return value;
  std::ostringstream os;
  os << std::strtod(value.c_str(), nullptr);
  return os.str();
}

// "12000 steps, 4 h 0 min of training, best validation PSNR 19.89 dB"
std::string training_text(const Provenance& p) {
  if (p.trained_steps.empty()) return "not recorded (a file from before 2026-11-24, or an imported state dict)";
  std::ostringstream os;
  os << p.trained_steps << " steps";
  if (!p.train_seconds.empty() && is_decimal_number(p.train_seconds))
    os << ", " << format_duration(std::strtod(p.train_seconds.c_str(), nullptr)) << " of training";
  if (!p.best_val_psnr.empty() && is_decimal_number(p.best_val_psnr))
    os << ", best validation PSNR " << std::fixed << std::setprecision(2)
       << std::strtod(p.best_val_psnr.c_str(), nullptr) << " dB";
  return os.str();
}

std::string scores_text(const std::string& json_text) {
  if (json_text.empty()) return "none recorded (flatnet export --scores SET=EVAL_DIR records them)";
  const auto all = nlohmann::json::parse(json_text, nullptr, false);
  if (all.is_discarded() || !all.is_object()) return "(unreadable: " + printable(json_text.substr(0, 60)) + ")";
  std::ostringstream os;
  os << std::fixed;
  for (const auto& [set, s] : all.items()) {
    auto value = [&](const char* key, int digits) {
      if (!s.is_object() || !s.contains(key) || !s[key].is_number()) return std::string("-");
      std::ostringstream v;
      v << std::fixed << std::setprecision(digits) << s[key].get<double>();
      return v.str();
    };
    os << "\n  " << std::left << std::setw(10) << printable(set) << " PSNR " << value("psnr", 2) << " dB, SSIM "
       << value("ssim", 3) << ", NIQE " << value("niqe", 2) << ", colour kept " << value("colour_kept", 2)
       << ", detail kept " << value("detail_kept", 2) << " (" << value("images", 0) << " images)";
  }
  return os.str();
}

}  // namespace

std::string recorded_scores(const std::vector<std::string>& items, const std::string& method) {
  nlohmann::json recorded = nlohmann::json::object();
  for (const auto& [set, where] : named_paths(items, "--scores")) {
    std::filesystem::path file = where;
    if (std::filesystem::is_directory(file)) file /= "scores.json";
    const auto all = nlohmann::json::parse(read_file_text(file, 1u << 20), nullptr, false);
    require(!all.is_discarded() && all.is_object(), file, "is not a scores.json that `flatnet eval` writes");
    std::vector<std::string> methods;
    for (const auto& [name, _] : all.items())
      if (name != "ground truth") methods.push_back(name);
    std::string chosen = method;
    if (chosen.empty()) {
      require(
          methods.size() == 1, file,
          "holds " + std::to_string(methods.size()) + " methods; name one with --method (" + join(methods, ", ") + ")");
      chosen = methods[0];
    }
    require(all.contains(chosen) && all[chosen].is_object(), file,
            "has no method '" + chosen + "' (it has " + join(methods, ", ") + ")");
    auto entry = all[chosen];
    entry["method"] = chosen;
    recorded[set] = entry;
  }
  return recorded.dump();
}

namespace {

struct InfoSettings {
  std::filesystem::path file;
  bool json = false;
};

const FlagTable<InfoSettings>& info_flags() {
  static const FlagTable<InfoSettings> rows = {
      {"file", &InfoSettings::file, "model file (.flatnet) or training checkpoint (.ckpt)"},
      {"json", &InfoSettings::json, "print one JSON object instead of text"},
  };
  return rows;
}

struct OptionsSettings {
  std::string prefix, for_command = "train";
  std::filesystem::path defaults;
  bool markdown = false, check = false;
};

const FlagTable<OptionsSettings>& options_flags() {
  using S = OptionsSettings;
  static const FlagTable<S> rows = {
      {"prefix", &S::prefix, "only keys starting with this (train., loss.lr ...)"},
      {"for", &S::for_command,
       "train (flatnet train), mask (mask train) or separable (mask separable): a trainer's config settings; camera: "
       "a camera file's keys; or any other command (simulate, recon, 'eval fit-niqe' ...): its flags"},
      {"defaults", &S::defaults, "a defaults file to describe instead (a .yaml)"},
      {"markdown", &S::markdown, "print a Markdown table"},
      {"check", &S::check,
       "check that every command's flags agree with their option structs (the defaults --help shows are the "
       "structs', and each flag sets its member)"},
  };
  return rows;
}

}  // namespace

int info(int argc, char** argv) {
  cxxopts::Options o("flatnet info",
                     "What a model file or checkpoint holds: architecture, camera, recipe, "
                     "training, recorded scores and its SHA-256.");
  add_flags(o, info_flags());
  o.parse_positional({"file"});
  o.positional_help("FILE");
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  InfoSettings settings;
  read_flags(r, info_flags(), settings);
  require(r.count("file"), "info", "a model file is required: flatnet info MODEL.flatnet");
  const auto& path = settings.file;
  const bool checkpoint = is_checkpoint_file(path);
  bool average = false;
  auto m = checkpoint ? model_from_checkpoint(path, &average) : load_model_file(path);
  const auto& spec = m.spec;
  int64_t parameters = 0;
  for (const auto& p : m.generator->parameters()) parameters += p.numel();
  const auto& cam = m.camera;
  const auto hash = sha256_hex(path);
  const auto bytes = std::filesystem::file_size(path);

  if (settings.json) {
    nlohmann::json j = {
        {"file", path.string()},
        {"bytes", bytes},
        {"sha256", hash},
        {"kind", checkpoint ? "checkpoint" : "model"},
        {"format_version", m.format_version},
        {"first_stage", first_stage_text(spec)},
        {"enhancer", enhancer_text(spec)},
        {"level_input", spec.level_input},
        {"consistency", {{"strength", spec.consistency_strength}, {"blur", spec.consistency_blur}}},
        {"parameters", parameters},
        {"camera", {{"name", cam.name}, {"crop", {cam.raw.crop[2], cam.raw.crop[3]}}, {"scene", cam.scene_size}}},
        {"losses", join_nonzero_losses(m)},
        {"model_spec", model_spec_yaml(spec)},
        {"config", m.recipe},
    };
    for (const auto& [key, field] : provenance_fields()) {
      const auto& value = m.provenance.*field;
      if (value.empty()) continue;
      const auto parsed = key == "scores" ? nlohmann::json::parse(value, nullptr, false) : nlohmann::json();
      j[key] = key == "scores" && !parsed.is_discarded() ? parsed : nlohmann::json(value);
    }
    std::cout << j.dump(2) << "\n";
    return 0;
  }
  const auto& p = m.provenance;
  std::cout << std::left;
  // Every string here comes from the file: escaped, so metadata cannot drive the terminal.
  auto line = [](const char* label, const std::string& text) {
    std::cout << std::setw(10) << label << printable(text) << "\n";
  };
  line("file", path.string() + " (" + std::to_string(bytes) + " bytes)");
  line("sha256", hash);
  line("kind", std::string(checkpoint ? "training checkpoint" : "model file") + ", format " +
                   std::to_string(m.format_version) + (checkpoint && average ? " (its moving average shown)" : ""));
  line("model", first_stage_text(spec) + " -> " + enhancer_text(spec) +
                    (spec.level_input ? ", light level as input" : "") + consistency_text(spec) + "; " +
                    std::to_string(parameters) + " parameters");
  line("camera", cam.name + ": " + std::to_string(cam.raw.crop[2]) + "x" + std::to_string(cam.raw.crop[3]) +
                     " measurement -> " + std::to_string(cam.scene_size) + "x" + std::to_string(cam.scene_size) +
                     " scene (" + data_key(&DataOptions::camera) + " " +
                     recorded_or_unknown(m, data_key(&DataOptions::camera)) + ")");
  const auto source = m.recorded("data.source");
  line("data", source == "simulate"
                   ? "simulated display captures of " + recorded_or_unknown(m, data_key(&DataOptions::images))
               : source == "dataset" ? "captures in " + recorded_or_unknown(m, data_key(&DataOptions::dataset))
                                     : "not recorded");
  std::ostringstream recipe;
  recipe << join_nonzero_losses(m) << "; batch " << recorded_or_unknown(m, train_key(&TrainOptions::batch)) << ", crop "
         << recorded_or_unknown(m, train_key(&TrainOptions::crop)) << ", lr "
         << recorded_or_unknown(m, train_key(&TrainOptions::lr)) << ", precision "
         << recorded_or_unknown(m, train_key(&TrainOptions::precision));
  line("recipe", recipe.str());
  line("training", training_text(p));
  if (!p.source.empty()) line("source", p.source);
  if (!p.written_at.empty()) line("written", p.written_at + (p.written_on.empty() ? "" : " on " + p.written_on));
  std::cout << std::setw(10) << "scores" << scores_text(p.scores) << "\n";  // escaped piece by piece
  std::cout << "(`flatnet info --json` adds the model spec and the recorded training config)\n";
  return 0;
}

namespace {

// The rows of a command's own flags (cli/flag_rows.hpp), as `flatnet options` prints settings.
// One line of `flatnet options`: a setting (a config key or a flag), its default, what it does and
// its range; or, with `markdown`, a table row (a '|' in the text would end the cell).
void print_setting(const std::string& name, std::string value, const std::string& range, const std::string& doc,
                   bool markdown, int name_width) {
  if (value.empty()) value = "\"\"";
  if (markdown) {
    static const std::regex pipe("\\|");
    const auto cell = [](const std::string& text) { return std::regex_replace(text, pipe, "\\|"); };
    std::cout << "| `" << name << "` | `" << cell(value) << "` | " << range << " | " << cell(doc) << " |\n";
    return;
  }
  std::cout << std::left << std::setw(name_width) << name << " " << std::setw(14) << value << " " << doc;
  if (!range.empty()) std::cout << " [" << range << "]";
  std::cout << "\n";
}

int print_command_flags(const CommandFlags& command, const std::string& prefix, bool markdown) {
  if (markdown) std::cout << "| flag | default | range | what it does |\n|---|---|---|---|\n";
  size_t shown = 0;
  for (const auto& f : command.describe()) {
    if (f.flag.compare(0, prefix.size(), prefix) != 0) continue;
    ++shown;
    print_setting("--" + f.flag, f.is_switch ? "(switch)" : f.default_text, f.range, f.doc, markdown, 24);
  }
  require(shown > 0, "--for " + command.command, "has no flag starting with '" + prefix + "'");
  return 0;
}

// `flatnet options --for camera`: every key a camera file may hold (io/camera_config.hpp's rows).
int print_camera_keys(const std::string& prefix, bool markdown) {
  if (markdown) std::cout << "| key | default | range | what it is |\n|---|---|---|---|\n";
  size_t shown = 0;
  for (const auto& k : camera_file_keys()) {
    if (k.key.compare(0, prefix.size(), prefix) != 0) continue;
    ++shown;
    print_setting(k.key, k.default_text.empty() ? "\"\"" : k.default_text, k.range, k.doc, markdown, 24);
  }
  require(shown > 0, "--for camera", "has no key starting with '" + prefix + "'");
  return 0;
}

// A value for `row` other than its default, inside its range: what --check gives the flag.
std::string other_value(const FlagDescription& row, const std::string& range_lo) {
  if (!range_lo.empty() && range_lo != row.default_text) return range_lo;
  return row.default_text == "1" ? "2" : "1";
}

// Holds every command's flags to their structs: with no flag given each member keeps its struct's
// default; each numeric or text flag given a value sets its member to it; a flag given its default's
// text reads back the same default. Returns the problems found.
std::vector<std::string> check_command_flags() {
  std::vector<std::string> problems;
  for (const auto& command : every_command_flags()) {
    const auto where = "flatnet " + command.command + ": ";
    const auto rows = command.describe();
    const auto untouched = command.parse({});
    for (const auto& row : rows) {
      const auto value = untouched.find(row.flag);
      if (value == untouched.end() || value->second != row.default_text)
        problems.push_back(where + "--" + row.flag + " without the flag is not the struct's default " +
                           row.default_text);
      if (row.is_switch) {
        if (command.parse({"--" + row.flag}).at(row.flag) != "true")
          problems.push_back(where + "the switch --" + row.flag + " does not set its member");
        continue;
      }
      const bool number = is_decimal_number(row.default_text);
      try {
        if (!row.default_text.empty() &&
            command.parse({"--" + row.flag, row.default_text}).at(row.flag) != row.default_text)
          problems.push_back(where + "--" + row.flag + " " + row.default_text + " does not read back as its default");
      } catch (const Error& e) {  // a number's default may be a sentinel outside what a user gives (--lambda 0)
        if (!number) problems.push_back(where + "--" + row.flag + " " + row.default_text + ": " + e.what());
      }
      const auto given = number ? other_value(row, "") : std::string("flag-check-text");
      try {
        const auto got = command.parse({"--" + row.flag, given}).at(row.flag);
        if (got != given) problems.push_back(where + "--" + row.flag + " " + given + " set its member to " + got);
      } catch (const Error&) {  // a text with its own reader (on|off, a list), or a range that excludes it
      }
    }
  }
  return problems;
}

}  // namespace

// flatnet options: every setting a trainer reads, with its default, range and documentation,
// from the defaults file where they are declared (io/config.hpp, describe_settings); or a
// command's own flags, from its rows.
int options(int argc, char** argv) {
  cxxopts::Options o("flatnet options",
                     "Every setting of a trainer's config, with its default, its range and what it does. Set them in "
                     "an experiment file (--config) or with --set key=value.");
  add_flags(o, options_flags());
  o.parse_positional({"prefix"});
  o.positional_help("[PREFIX]");
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  OptionsSettings settings;
  read_flags(r, options_flags(), settings);
  if (settings.check) {
    const auto problems = check_command_flags();
    size_t flags = 0;
    const auto commands = every_command_flags();
    for (const auto& c : commands) flags += c.describe().size();
    for (const auto& p : problems) std::cout << p << "\n";
    std::cout << commands.size() << " flag tables, " << flags << " flags: "
              << (problems.empty() ? "every default is its struct's and every flag sets its member"
                                   : std::to_string(problems.size()) + " problems")
              << "\n";
    return problems.empty() ? 0 : 1;
  }
  const auto& which = settings.for_command;
  const auto& prefix = settings.prefix;
  const bool markdown = settings.markdown;
  if (which == "camera") return print_camera_keys(prefix, markdown);
  const std::map<std::string, std::string> files = {
      {"train", "defaults.yaml"}, {"mask", "mask_defaults.yaml"}, {"separable", "separable_defaults.yaml"}};
  if (!files.count(which) && !r.count("defaults")) {
    std::string names;
    for (const auto& command : every_command_flags()) {
      if (command.command == which) return print_command_flags(command, prefix, markdown);
      names += ", " + command.command;
    }
    throw Error("--for",
                "'" + printable(which) + "' is no command with flags: give train, mask, separable, camera" + names);
  }
  const std::filesystem::path file = r.count("defaults") ? settings.defaults : data_dir() / "configs" / files.at(which);
  if (markdown) std::cout << "| key | default | range | what it does |\n|---|---|---|---|\n";
  size_t shown = 0;
  for (const auto& s : describe_settings(file)) {
    if (s.key.compare(0, prefix.size(), prefix) != 0) continue;
    ++shown;
    print_setting(s.key, s.default_value, s.range, s.doc, markdown, 34);
  }
  require(shown > 0, file, "has no setting starting with '" + prefix + "'");
  return 0;
}

std::vector<CommandFlags> every_command_flags() {
  return {simulate_command_flags(),
          calibrate_command_flags(),
          recon_command_flags(),
          eval_command_flags(),
          fit_niqe_command_flags(),
          report_command_flags(),
          report_inversion_command_flags(),
          infer_command_flags(),
          mask_train_command_flags(),
          mask_separable_command_flags(),
          mask_eval_command_flags(),
          mask_report_command_flags(),
          mask_camera_command_flags(),
          bench_command_flags(),
          demo_command_flags(),
          cameras_command_flags(),
          capture_command_flags(),
          capture_dataset_command_flags(),
          capture_calibration_command_flags(),
          live_command_flags(),
          train_command_flags(),
          export_command_flags(),
          import_command_flags(),
          command_flags("info", info_flags()),
          command_flags("options", options_flags()),
          command_flags("every command", common_flags(), precision_flags(), force_folder_flags(), lpips_flags())};
}

}  // namespace flatnet::cli
