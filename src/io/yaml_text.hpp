#pragma once
// YAML as flatnet reads it (configs, camera files, the settings model files embed): one document,
// no key given twice in a mapping, bounded size and nesting. YAML itself allows a second document
// and duplicate keys, and a reader that silently took the first or the last would disagree with
// the user's intent; both are errors here, naming the file.
#include <cstdint>
#include <filesystem>
#include <string>

#include <yaml-cpp/yaml.h>

namespace flatnet {

// 4 MiB: defaults.yaml is 6 KB; the largest file flatnet writes is a camera file listing its most hot
// pixels (kMaxHotPixels pairs of 5-digit numbers: about 1.6 MB).
constexpr uint64_t kMaxYamlBytes = 4u << 20;

// Parses `text` (from `where`, named in errors).
YAML::Node parse_yaml_document(const std::string& text, const std::filesystem::path& where);
// A string as one double-quoted YAML scalar (escapes included), for YAML written by hand: a camera
// named `FlatCam: lab v2` or `#1` must read back as that name, not as a mapping or a comment.
std::string yaml_quoted(const std::string& text);
// Reads and parses a YAML file: a regular file of at most kMaxYamlBytes.
YAML::Node load_yaml_file(const std::filesystem::path& path);

}  // namespace flatnet
