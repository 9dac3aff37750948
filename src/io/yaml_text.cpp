#include "io/yaml_text.hpp"

#include <set>
#include <sstream>

#include <yaml-cpp/eventhandler.h>
#include <yaml-cpp/parser.h>

#include "core/error.hpp"
#include "core/util.hpp"

namespace flatnet {
namespace {

constexpr int kMaxYamlDepth = 32;
// Nodes a document may expand to, aliases counted at every use: defaults.yaml has ~200, and the
// largest file flatnet writes is a camera file listing its most hot pixels (kMaxHotPixels, 100,000
// [row, col] pairs: 3 nodes each), so the bound is that and room to spare. A "billion laughs" alias
// bomb of 600 bytes expands to 10^9 nodes; the walk stops at the bound, so it and every later walk of
// the same tree stays bounded (400,000 nodes: about 0.1 s).
constexpr int64_t kMaxYamlNodes = 400000;

void check_keys(const YAML::Node& node, const std::filesystem::path& where, int depth, int64_t& nodes) {
  require(depth <= kMaxYamlDepth, where, "YAML nests deeper than " + std::to_string(kMaxYamlDepth) + " levels");
  require(++nodes <= kMaxYamlNodes, where,
          "YAML expands to more than " + std::to_string(kMaxYamlNodes) +
              " nodes (aliases that repeat aliases?); flatnet's own files need at most 300,000");
  if (node.IsMap()) {
    std::set<std::string> seen;
    for (const auto& kv : node) {
      const auto key = kv.first.IsScalar() ? kv.first.Scalar() : std::string("(a non-scalar key)");
      require(seen.insert(key).second, where, "YAML key '" + printable(key) + "' is given twice in one mapping");
      check_keys(kv.second, where, depth + 1, nodes);
    }
  } else if (node.IsSequence()) {
    for (const auto& item : node) check_keys(item, where, depth + 1, nodes);
  }
}

// Counts a text's documents by their parse events alone, building no nodes, and stops at 2: yaml-cpp
// 0.7's LoadAll never ends on a text whose first token is a ',' (", 2" is an endless run of empty
// documents, and its memory grows until the process dies; found by scripts/fuzz.sh).
int document_count(const std::string& text) {
  struct Ignore : YAML::EventHandler {
    void OnDocumentStart(const YAML::Mark&) override {}
    void OnDocumentEnd() override {}
    void OnNull(const YAML::Mark&, YAML::anchor_t) override {}
    void OnAlias(const YAML::Mark&, YAML::anchor_t) override {}
    void OnScalar(const YAML::Mark&, const std::string&, YAML::anchor_t, const std::string&) override {}
    void OnSequenceStart(const YAML::Mark&, const std::string&, YAML::anchor_t, YAML::EmitterStyle::value) override {}
    void OnSequenceEnd() override {}
    void OnMapStart(const YAML::Mark&, const std::string&, YAML::anchor_t, YAML::EmitterStyle::value) override {}
    void OnMapEnd() override {}
  } ignore;
  std::istringstream in(text);
  YAML::Parser parser(in);
  int count = 0;
  while (count < 2 && parser.HandleNextDocument(ignore)) ++count;
  return count;
}

}  // namespace

YAML::Node parse_yaml_document(const std::string& text, const std::filesystem::path& where) {
  require(
      text.size() <= kMaxYamlBytes, where,
      "YAML text of " + std::to_string(text.size()) + " bytes is over the limit of " + std::to_string(kMaxYamlBytes));
  std::vector<YAML::Node> documents;
  try {
    const auto count = document_count(text);
    require(count <= 1, where,
            "holds more than one YAML document ('---', or a stray ',' before the first); flatnet reads one");
    if (count == 1) documents.push_back(YAML::Load(text));
  } catch (const YAML::Exception& e) {
    throw Error(where, std::string("invalid YAML: ") + e.what());
  }
  if (documents.empty()) return YAML::Node();
  int64_t nodes = 0;
  check_keys(documents.front(), where, 0, nodes);
  return documents.front();
}

std::string yaml_quoted(const std::string& text) {
  YAML::Emitter e;
  e << YAML::DoubleQuoted << text;
  return e.c_str();
}

YAML::Node load_yaml_file(const std::filesystem::path& path) {
  return parse_yaml_document(read_file_text(path, kMaxYamlBytes), path);
}

}  // namespace flatnet
