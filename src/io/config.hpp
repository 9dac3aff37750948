#pragma once
// Experiment configuration: configs/defaults.yaml defines every key (with comments and default
// values); an experiment file overrides some of them (and may name a `base:` file it extends), and
// `--set key=value` overrides last. A key that defaults.yaml does not define is an error that names
// the nearest known key. Read at the edges only: the CLI, the experiment runner (train/experiment)
// and model files (which embed it) turn it into option structs; no library constructor takes it.
#include <filesystem>
#include <map>
#include <string>
#include <vector>

namespace flatnet {

// A number setting's range, declared by the layer that owns the setting (its option table's row,
// io/option_table.hpp) and registered here, so that every config is checked when it is loaded,
// whichever layer reads the key later.
struct RangeRow {
  std::string key;
  double lo = 0, hi = 0;
  std::string meaning;  // "1 to 4096 filters"; empty for a path row
  bool path = false;    // the value is a file or folder (Config::path), not a number
};
// Adds rows to the checks Config::check_ranges makes (train/options.hpp register_option_tables
// registers every table's, once, at a program's start).
bool register_ranges(const std::vector<RangeRow>& rows);
// "" when `text` is a finite decimal number within the row's range, else what is wrong.
std::string range_problem(const std::string& text, const RangeRow& row);

class Config {
 public:
  // defaults.yaml, then `experiment` (may be empty) and its bases, then the `sets` ("a.b=value").
  static Config load(const std::filesystem::path& experiment, const std::vector<std::string>& sets = {},
                     const std::filesystem::path& defaults = default_path());
  // Defaults overridden by YAML text (the merged config a checkpoint or model file embeds).
  static Config from_text(const std::string& yaml, const std::filesystem::path& where,
                          const std::filesystem::path& defaults = default_path());
  static std::filesystem::path default_path();  // data_dir()/configs/defaults.yaml
  // Settings as given by dotted key, with no defaults file (a model file's stored spec, whose
  // schema supplies every key); ranges checked, errors naming `where`. No value is a relative path.
  static Config from_values(const std::map<std::string, std::string>& values, const std::string& where);

  // Overrides one key ("a.b=value"); `where` names the source in errors.
  void set(const std::string& assignment, const std::string& where = "--set");

  std::string str(const std::string& key) const;
  double num(const std::string& key) const;
  int64_t integer(const std::string& key) const;
  bool flag(const std::string& key) const;
  // A path value, resolved against the folder of the file that set it ("" stays ""). Only the
  // keys is_path_key names are paths.
  std::filesystem::path path(const std::string& key) const;
  static bool is_path_key(const std::string& key);

  // Throws (naming `where`, the key and its range) unless every number is finite and in its
  // range (config.cpp's table and the rows the layers register); load and from_text call it, and
  // so must code that calls set().
  void check_ranges(const std::string& where = "--set") const;
  // The keys whose ranges are checked (a test holds them and the defaults files together).
  static std::vector<std::string> ranged_keys();

  // Every key with its value, as nested YAML (what checkpoints and model files embed).
  std::string to_yaml() const;
  const std::map<std::string, std::string>& values() const { return values_; }

 private:
  void merge_file(const std::filesystem::path& file, int depth);
  void merge_node_text(const std::string& yaml, const std::filesystem::path& where, const std::filesystem::path& base);
  void assign(const std::string& key, const std::string& value, const std::string& where,
              const std::filesystem::path& base);
  const std::string& lookup(const std::string& key) const;

  std::map<std::string, std::string> values_;  // dotted key -> scalar text
  std::map<std::string, std::filesystem::path> bases_;
};

// A YAML mapping's scalars by dotted key (model.unet.width -> 32), as written: no defaults
// merged, no path resolved (errors name `where`).
std::map<std::string, std::string> flat_yaml(const std::string& text, const std::filesystem::path& where);

// One setting of a defaults file as `flatnet options` lists it: its default, its range (the
// number table in config.cpp; empty for text, flags and paths) and its documentation (the comment
// on the key's line in the file, joined with the comment lines indented below it). The defaults
// file is where a setting's default and documentation are declared, the range table where its
// range is, and a trainer's option table (train/options.hpp) binds it to the struct member it
// fills; a test holds the three together.
struct SettingDoc {
  std::string key, default_value, range, doc;
};
std::vector<SettingDoc> describe_settings(const std::filesystem::path& defaults);
// Each setting's one doc text by dotted key: its comment in a defaults file (what describe_settings
// prints, and a flag's --help).
std::map<std::string, std::string> setting_docs(const std::filesystem::path& defaults);

// The known key nearest to `key` by edit distance, or "" when none is a typo's distance away.
std::string nearest_key(const std::string& key, const std::vector<std::string>& known);
// What to tell a user who gave an unknown key: the nearest key, else the known keys of its section.
std::string unknown_key_hint(const std::string& key, const std::vector<std::string>& known);

}  // namespace flatnet
