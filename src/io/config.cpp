#include "io/config.hpp"

#include <cmath>
#include <fstream>
#include <optional>
#include <regex>
#include <sstream>

#include <yaml-cpp/yaml.h>

#include "core/error.hpp"
#include "core/util.hpp"
#include "io/yaml_text.hpp"

namespace flatnet {

namespace {

// Flattens a YAML mapping into dotted keys with scalar (or flow-sequence) text values.
void flatten(const YAML::Node& node, const std::string& prefix, std::map<std::string, std::string>& out) {
  for (const auto& kv : node) {
    const auto key = prefix.empty() ? kv.first.as<std::string>() : prefix + "." + kv.first.as<std::string>();
    if (out.count(key)) throw Error("config: setting '" + key + "' is given twice");
    if (kv.second.IsMap()) {
      flatten(kv.second, key, out);
    } else if (kv.second.IsSequence()) {
      YAML::Emitter e;
      e << YAML::Flow << kv.second;
      out[key] = e.c_str();
    } else if (kv.second.IsNull()) {
      out[key] = "";
    } else {
      out[key] = kv.second.as<std::string>();
    }
  }
}

YAML::Node parse_yaml(const std::string& text, const std::filesystem::path& where) {
  auto n = parse_yaml_document(text, where);
  require(n.IsMap() || n.IsNull(), where, "expected a mapping of settings");
  return n;
}

// A stored list setting is its flow text, "[a, b]": a sequence of scalars. Anything else that starts
// with '[' (a string holding anchors, nested lists, unbalanced brackets) is a string, written as one.
std::optional<YAML::Node> flat_list(const std::string& value) {
  if (value.empty() || value.front() != '[') return std::nullopt;
  try {
    auto node = parse_yaml_document(value, "config value");
    if (!node.IsSequence()) return std::nullopt;
    for (const auto& item : node)
      if (!item.IsScalar()) return std::nullopt;
    return node;
  } catch (const std::exception&) {
    return std::nullopt;
  }
}

std::string read_file(const std::filesystem::path& p) { return read_file_text(p, kMaxYamlBytes); }

size_t edit_distance(const std::string& a, const std::string& b) {
  std::vector<size_t> prev(b.size() + 1), cur(b.size() + 1);
  for (size_t j = 0; j <= b.size(); ++j) prev[j] = j;
  for (size_t i = 1; i <= a.size(); ++i) {
    cur[0] = i;
    for (size_t j = 1; j <= b.size(); ++j)
      cur[j] = std::min({prev[j] + 1, cur[j - 1] + 1, prev[j - 1] + (a[i - 1] == b[j - 1] ? 0 : 1)});
    std::swap(prev, cur);
  }
  return prev[b.size()];
}

}  // namespace

namespace {

std::vector<RangeRow>& registered_ranges() {
  static std::vector<RangeRow> rows;
  return rows;
}

// The number rows the owning layers registered (their option tables; path rows left out).
std::vector<RangeRow> all_ranges() {
  std::vector<RangeRow> rows;
  for (const auto& row : registered_ranges())
    if (!row.path) rows.push_back(row);
  return rows;
}

}  // namespace

bool register_ranges(const std::vector<RangeRow>& rows) {
  auto& all = registered_ranges();
  all.insert(all.end(), rows.begin(), rows.end());
  return true;
}

std::string range_problem(const std::string& text, const RangeRow& row) {
  return number_problem(text, NumberRule{row.key.c_str(), row.lo, row.hi, row.meaning.c_str()});
}

std::map<std::string, std::string> flat_yaml(const std::string& text, const std::filesystem::path& where) {
  std::map<std::string, std::string> flat;
  try {
    flatten(parse_yaml(text, where), "", flat);
  } catch (const YAML::Exception& e) {
    throw Error(where, std::string("invalid settings: ") + e.what());
  }
  return flat;
}

std::vector<std::string> Config::ranged_keys() {
  std::vector<std::string> keys;
  for (const auto& row : all_ranges()) keys.push_back(row.key);
  return keys;
}

void Config::check_ranges(const std::string& where) const {
  // A program that reads configs registers the option tables first (train/options.hpp
  // register_option_tables): without them no number would be checked.
  if (registered_ranges().empty())
    throw std::logic_error("config: no option ranges registered (call register_option_tables() at start-up)");
  for (const auto& row : all_ranges()) {
    const auto it = values_.find(row.key);
    if (it == values_.end()) continue;
    const auto problem = range_problem(it->second, row);
    if (!problem.empty())
      throw Error(where + ": " + row.key + " = " + printable(it->second) + " " + problem + ": " + row.meaning);
  }
}

namespace {

std::string trimmed(const std::string& s) {
  const auto b = s.find_first_not_of(" \t"), e = s.find_last_not_of(" \t\r");
  return b == std::string::npos ? "" : s.substr(b, e - b + 1);
}

// Where a YAML comment starts in the text after a key's colon: a '#' outside quotes, at the start
// or after a blank (npos: none).
size_t comment_start(const std::string& rest) {
  char quote = 0;
  for (size_t i = 0; i < rest.size(); ++i) {
    const char ch = rest[i];
    if (quote) {
      if (ch == quote) quote = 0;
    } else if (ch == '"' || ch == '\'') {
      quote = ch;
    } else if (ch == '#' && (i == 0 || rest[i - 1] == ' ' || rest[i - 1] == '\t')) {
      return i;
    }
  }
  return std::string::npos;
}

// The documentation comments of a block-style YAML file (the defaults files), by dotted key: the
// text after '#' on a key's line, joined with the comment-only lines below it that are indented
// deeper than the key. A key with no value on its line opens a section.
std::map<std::string, std::string> key_comments(const std::string& text) {
  static const std::regex key_line(R"(^( *)([A-Za-z_][A-Za-z0-9_]*):(.*)$)");
  static const std::regex comment_line(R"(^( *)#(.*)$)");
  std::map<std::string, std::string> docs;
  std::vector<std::pair<size_t, std::string>> sections;  // indent, name
  std::string last_key;
  size_t last_indent = 0;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) {
    std::smatch m;
    if (std::regex_match(line, m, key_line)) {
      const size_t indent = static_cast<size_t>(m[1].length());
      while (!sections.empty() && sections.back().first >= indent) sections.pop_back();
      std::string key;
      for (const auto& section : sections) key += section.second + ".";
      key += m[2].str();
      const std::string rest = m[3].str();
      const auto hash = comment_start(rest);
      const auto value = trimmed(rest.substr(0, hash));
      last_key.clear();
      if (value.empty()) {
        sections.emplace_back(indent, m[2].str());
        continue;
      }
      docs[key] = hash == std::string::npos ? "" : trimmed(rest.substr(hash + 1));
      last_key = key;
      last_indent = indent;
    } else if (std::regex_match(line, m, comment_line) && !last_key.empty() &&
               static_cast<size_t>(m[1].length()) > last_indent) {
      auto& doc = docs[last_key];
      doc += (doc.empty() ? "" : " ") + trimmed(m[2].str());
    } else {
      last_key.clear();
    }
  }
  return docs;
}

}  // namespace

std::vector<SettingDoc> describe_settings(const std::filesystem::path& defaults) {
  const auto config = Config::load({}, {}, defaults);
  const auto docs = key_comments(read_file(defaults));
  std::vector<SettingDoc> out;
  for (const auto& [key, value] : config.values()) {
    SettingDoc d{key, value, "", ""};
    for (const auto& row : all_ranges())
      if (key == row.key) d.range = row.meaning;
    if (const auto it = docs.find(key); it != docs.end()) d.doc = it->second;
    out.push_back(d);
  }
  return out;
}

std::map<std::string, std::string> setting_docs(const std::filesystem::path& defaults) {
  return key_comments(read_file(defaults));
}

std::string nearest_key(const std::string& key, const std::vector<std::string>& known) {
  std::string best;
  size_t best_d = SIZE_MAX;
  const auto last = key.substr(key.rfind('.') == std::string::npos ? 0 : key.rfind('.') + 1);
  for (const auto& k : known) {
    // Compare whole keys and also the last component, so "lr" finds "train.lr".
    const auto klast = k.substr(k.rfind('.') == std::string::npos ? 0 : k.rfind('.') + 1);
    const size_t d = std::min(edit_distance(key, k), edit_distance(last, klast) + 1);
    if (d < best_d) best_d = d, best = k;
  }
  // A typo is a few edits away; anything further is another word, not worth suggesting.
  const size_t close = std::max<size_t>(2, last.size() / 3);
  return best_d <= close ? best : std::string();
}

std::string unknown_key_hint(const std::string& key, const std::vector<std::string>& known) {
  const auto nearest = nearest_key(key, known);
  if (!nearest.empty()) return "did you mean '" + nearest + "'?";
  const auto dot = key.find('.');
  const auto section = key.substr(0, dot + 1);  // "train." (empty for a key without a section)
  std::string same_section;
  if (dot != std::string::npos)
    for (const auto& k : known)
      if (k.rfind(section, 0) == 0) same_section += (same_section.empty() ? "" : ", ") + k.substr(section.size());
  if (same_section.empty()) return "no setting is near it; `flatnet options` lists them";
  return "this command's " + key.substr(0, dot) + " settings: " + same_section;
}

std::filesystem::path Config::default_path() { return data_dir() / "configs" / "defaults.yaml"; }

Config Config::load(const std::filesystem::path& experiment, const std::vector<std::string>& sets,
                    const std::filesystem::path& defaults) {
  Config c;
  require(std::filesystem::exists(defaults), defaults, "missing defaults file");
  flatten(parse_yaml(read_file(defaults), defaults), "", c.values_);
  for (const auto& kv : c.values_) c.bases_[kv.first] = defaults.parent_path().parent_path();
  if (!experiment.empty()) c.merge_file(experiment, 0);
  for (const auto& s : sets) c.set(s);
  c.check_ranges((experiment.empty() ? std::string("config") : printable(experiment.string())) +
                 (sets.empty() ? "" : " with --set or a flag"));
  return c;
}

Config Config::from_text(const std::string& yaml, const std::filesystem::path& where,
                         const std::filesystem::path& defaults) {
  Config c = load({}, {}, defaults);
  c.merge_node_text(yaml, where, {});
  c.check_ranges(where.string());
  return c;
}

Config Config::from_values(const std::map<std::string, std::string>& values, const std::string& where) {
  Config c;
  c.values_ = values;
  c.check_ranges(where);
  return c;
}

void Config::merge_file(const std::filesystem::path& file, int depth) {
  require(std::filesystem::exists(file), file, "no such config file");
  require(!std::filesystem::is_directory(file), file, "is a folder; give a config .yaml file");
  require(depth < 8, file, "too many nested `base:` files");
  const auto text = read_file(file);
  const auto node = parse_yaml(text, file);
  if (node["base"]) merge_file(file.parent_path() / node["base"].as<std::string>(), depth + 1);
  merge_node_text(text, printable(file.string()), file.parent_path());  // the name shown in errors
}

void Config::merge_node_text(const std::string& yaml, const std::filesystem::path& where,
                             const std::filesystem::path& base) {
  std::map<std::string, std::string> flat;
  try {
    flatten(parse_yaml(yaml, where), "", flat);
  } catch (const YAML::Exception& e) {
    throw Error(where, std::string("invalid settings: ") + e.what());
  }
  for (const auto& kv : flat) {
    if (kv.first == "base") continue;
    assign(kv.first, kv.second, where.string(), base);
  }
}

void Config::assign(const std::string& key, const std::string& value, const std::string& where,
                    const std::filesystem::path& base) {
  if (!values_.count(key)) {
    if (key.size() > 200)
      throw Error(where + ": unknown setting '" + printable(key.substr(0, 60)) + "...' (" + std::to_string(key.size()) +
                  " characters)");
    std::vector<std::string> known;
    for (const auto& kv : values_) known.push_back(kv.first);
    throw Error(where + ": unknown setting '" + printable(key) + "' (" + unknown_key_hint(key, known) + ")");
  }
  // A list setting given a value that opens a list must be one ("[my photos" is a typo, named here
  // rather than by the YAML writer later).
  const auto& current = values_[key];
  if (!current.empty() && current.front() == '[' && !value.empty() && value.front() == '[' && !flat_list(value))
    throw Error(where + ": setting '" + printable(key) + "' is a list, but '" + printable(value) +
                "' is not a YAML list of values such as [a, b]");
  values_[key] = value;
  bases_[key] = base;
}

void Config::set(const std::string& assignment, const std::string& where) {
  const auto eq = assignment.find('=');
  if (eq == std::string::npos || eq == 0)
    throw Error(where + ": expected key=value, got '" + printable(assignment) + "'");
  assign(assignment.substr(0, eq), assignment.substr(eq + 1), where, std::filesystem::current_path());
}

const std::string& Config::lookup(const std::string& key) const {
  const auto it = values_.find(key);
  if (it == values_.end()) throw Error("config: no setting '" + printable(key) + "' in defaults.yaml");
  return it->second;
}

std::string Config::str(const std::string& key) const { return lookup(key); }

double Config::num(const std::string& key) const {
  const auto& v = lookup(key);
  if (is_decimal_number(v)) {
    const double d = std::strtod(v.c_str(), nullptr);
    if (std::isfinite(d)) return d;
  }
  throw Error("config: setting '" + key + "' must be a finite decimal number, got '" + printable(v) + "'");
}

int64_t Config::integer(const std::string& key) const {
  const double d = num(key);
  if (d != std::floor(d) || std::abs(d) > 9.0e15)
    throw Error("config: setting '" + key + "' must be an integer, got '" + printable(lookup(key)) + "'");
  return static_cast<int64_t>(d);
}

bool Config::flag(const std::string& key) const {
  const auto& v = lookup(key);
  if (v == "true" || v == "on" || v == "yes" || v == "1") return true;
  if (v == "false" || v == "off" || v == "no" || v == "0") return false;
  throw Error("config: setting '" + key + "' must be true or false, got '" + printable(v) + "'");
}

bool Config::is_path_key(const std::string& key) {
  for (const auto& row : registered_ranges())
    if (row.path && row.key == key) return true;
  return false;
}

std::filesystem::path Config::path(const std::string& key) const {
  if (!is_path_key(key))
    throw Error("config: setting '" + key + "' is not a path (no option table binds it to a path)");
  const auto& v = lookup(key);
  if (v.empty()) return {};
  std::filesystem::path p(v);
  if (p.is_absolute()) return p;
  const auto it = bases_.find(key);
  return it == bases_.end() || it->second.empty() ? p : it->second / p;
}

namespace {

struct KeyTree {
  std::map<std::string, KeyTree> children;
  std::string value;
  bool leaf = false;
};

void emit(YAML::Emitter& e, const KeyTree& t) {
  e << YAML::BeginMap;
  for (const auto& [k, child] : t.children) {
    e << YAML::Key << k << YAML::Value;
    if (!child.leaf)
      emit(e, child);
    else if (const auto list = flat_list(child.value))
      e << YAML::Flow << *list;
    else
      e << child.value;  // a string stays a string, whatever it holds
  }
  e << YAML::EndMap;
}

}  // namespace

std::string Config::to_yaml() const {
  KeyTree root;
  for (const auto& kv : values_) {
    KeyTree* node = &root;
    std::stringstream ss(kv.first);
    for (std::string part; std::getline(ss, part, '.');) node = &node->children[part];
    // A path key's relative value that names an existing file or folder is written resolved, so
    // the text means the same wherever it is read. Other values are never paths, whatever files
    // the working folder holds (a file called "1" must not turn train.batch=1 into a path).
    std::string value = kv.second;
    const auto base = bases_.count(kv.first) ? bases_.at(kv.first) : std::filesystem::path();
    if (is_path_key(kv.first) && !value.empty() && !base.empty() && std::filesystem::path(value).is_relative() &&
        std::filesystem::exists(base / value))
      value = std::filesystem::weakly_canonical(base / value).string();
    node->value = value;
    node->leaf = true;
  }
  YAML::Emitter e;
  emit(e, root);
  return std::string(e.c_str()) + "\n";
}

}  // namespace flatnet
