#pragma once
// An options struct bound to its config keys in one table: each row names the YAML key (relative
// to a prefix, for nested structs: "width" under "model.unet.") and the member it fills.
// read_options fills a struct through its table (no hand-written line per key), and
// defaults_differing lets a test hold the struct's C++ defaults to its defaults file. A setting's
// default and documentation are declared on its line of the defaults file and its range in
// io/config.cpp's table, checked when the config is loaded (`flatnet options` lists all three).
// The tables live beside the structs' readers: nn/model_file (the generator's), train/options
// (the trainers', the light augmentation's, co-design's, the mask's and its camera's).
#include <cstdint>
#include <filesystem>
#include <string>
#include <type_traits>
#include <variant>
#include <vector>

#include "io/config.hpp"

namespace flatnet {

template <class S>
struct OptionField {
  const char* key;
  std::variant<double S::*, int64_t S::*, int S::*, uint64_t S::*, bool S::*, std::string S::*,
               std::filesystem::path S::*>
      member;
};

// Fills every field of `s` from `c`, each key read as `prefix` + its row's key (a missing key or a
// value of the wrong kind is an error naming the key).
template <class S>
void read_options(const Config& c, const std::vector<OptionField<S>>& fields, S& s, const std::string& prefix = "") {
  for (const auto& f : fields)
    std::visit(
        [&](auto member) {
          using T = std::decay_t<decltype(s.*member)>;
          const auto key = prefix + f.key;
          if constexpr (std::is_same_v<T, double>) s.*member = c.num(key);
          else if constexpr (std::is_same_v<T, int64_t>) s.*member = c.integer(key);
          else if constexpr (std::is_same_v<T, int>) s.*member = static_cast<int>(c.integer(key));
          else if constexpr (std::is_same_v<T, uint64_t>) s.*member = static_cast<uint64_t>(c.integer(key));
          else if constexpr (std::is_same_v<T, bool>) s.*member = c.flag(key);
          else if constexpr (std::is_same_v<T, std::string>) s.*member = c.str(key);
          else s.*member = c.path(key);
        },
        f.member);
}

// "key: struct X, config Y" for every field whose default in S{} differs from `c`'s value (paths
// are not compared: a defaults file's are relative to the project).
template <class S>
std::vector<std::string> defaults_differing(const Config& c, const std::vector<OptionField<S>>& fields,
                                            const std::string& prefix = "") {
  std::vector<std::string> out;
  static const S defaults{};  // static: GCC 12 cannot see through the member pointers and warns of a local
  S from_config{};
  read_options(c, fields, from_config, prefix);
  for (const auto& f : fields)
    std::visit(
        [&](auto member) {
          using T = std::decay_t<decltype(defaults.*member)>;
          if constexpr (!std::is_same_v<T, std::filesystem::path>)
            if (!(defaults.*member == from_config.*member))
              out.push_back(prefix + f.key + ": the struct's default differs from " + c.str(prefix + f.key));
        },
        f.member);
  return out;
}

}  // namespace flatnet
