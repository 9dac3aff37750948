#pragma once
// A trainer's options bound to its config keys in one table: each row names the YAML key and the
// member it fills. The CLI reads a config through the table (no hand-written copy per key), and a
// test holds the struct's C++ defaults equal to its defaults file's (configs/*_defaults.yaml),
// so a library caller and a command-line user start from the same settings. A setting's default and
// documentation are declared on its line of the defaults file and its range in io/config.cpp's
// table, checked when the config is loaded (`flatnet options` shows all three).
#include <filesystem>
#include <string>
#include <type_traits>
#include <variant>
#include <vector>

#include "io/config.hpp"
#include "train/gan_trainer.hpp"
#include "train/mask_trainer.hpp"
#include "train/separable_trainer.hpp"

namespace flatnet {

template <class S>
struct OptionField {
  const char* key;
  std::variant<double S::*, int64_t S::*, int S::*, uint64_t S::*, bool S::*, std::string S::*,
               std::filesystem::path S::*>
      member;
};

// Fills every field of `s` from `c` (a missing key or a value of the wrong kind is an error naming the key).
template <class S>
void read_options(const Config& c, const std::vector<OptionField<S>>& fields, S& s) {
  for (const auto& f : fields)
    std::visit(
        [&](auto member) {
          using T = std::decay_t<decltype(s.*member)>;
          if constexpr (std::is_same_v<T, double>) s.*member = c.num(f.key);
          else if constexpr (std::is_same_v<T, int64_t>) s.*member = c.integer(f.key);
          else if constexpr (std::is_same_v<T, int>) s.*member = static_cast<int>(c.integer(f.key));
          else if constexpr (std::is_same_v<T, uint64_t>) s.*member = static_cast<uint64_t>(c.integer(f.key));
          else if constexpr (std::is_same_v<T, bool>) s.*member = c.flag(f.key);
          else if constexpr (std::is_same_v<T, std::string>) s.*member = c.str(f.key);
          else s.*member = c.path(f.key);
        },
        f.member);
}

// "key: struct X, config Y" for every field whose default in S{} differs from `c`'s value (paths
// are not compared: a defaults file's are relative to the project).
template <class S>
std::vector<std::string> defaults_differing(const Config& c, const std::vector<OptionField<S>>& fields) {
  std::vector<std::string> out;
  const S defaults{};
  S from_config{};
  read_options(c, fields, from_config);
  for (const auto& f : fields)
    std::visit(
        [&](auto member) {
          using T = std::decay_t<decltype(defaults.*member)>;
          if constexpr (!std::is_same_v<T, std::filesystem::path>)
            if (!(defaults.*member == from_config.*member)) out.push_back(std::string(f.key) + ": the struct's default differs from " + c.str(f.key));
        },
        f.member);
  return out;
}

// flatnet train: configs/defaults.yaml's train.*, loss.* and discriminator.* keys that map one to
// one onto TrainOptions (train.schedule and train.precision are parsed by train_options). Its
// C++ defaults are the library's (the thesis's recipe), not defaults.yaml's.
const std::vector<OptionField<TrainOptions>>& train_fields();
// mask train: configs/mask_defaults.yaml's train.* keys.
const std::vector<OptionField<MaskTrainOptions>>& mask_train_fields();
// mask separable: configs/separable_defaults.yaml (codes.init is resolved by the caller: mls, random or a file).
const std::vector<OptionField<SeparableTrainOptions>>& separable_train_fields();

}  // namespace flatnet
