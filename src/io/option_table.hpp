#pragma once
// The option schema: an options struct bound to its config keys in one table. Each row names the
// YAML key (relative to a prefix: "unet.width" under "model."), the member it fills (or, for a
// choice, how its text is read), a number's range with what it means and, optionally, the
// command-line flag that sets it; the default is the struct's own (S{}). A setting's one doc text
// is its comment in the command's defaults file (configs/defaults.yaml ...), which `flatnet options`
// and a flag's --help both print; a test holds each file's keys, values and comments to the rows.
// read_options fills a struct through its table (no hand-written line per key), range_rows gives the
// ranges to register with the config (io/config.hpp register_ranges, the only range table), and
// defaults_differing lets a test hold the struct's defaults to its defaults file.
// The tables live beside the structs' readers: nn/model_spec (the model's), train/options (the
// trainers', the light augmentation's, co-design's, the mask's and its camera's).
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <iomanip>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <variant>
#include <vector>

#include "io/config.hpp"

namespace flatnet {

// A setting whose text its reader turns into the member (an enum's name, "mls | random | a file").
template <class S>
struct Choice {
  void (*read)(const Config& c, const std::string& key, S& s);  // fills the member; errors name `key`
  std::string (*text)(const S& s) = nullptr;  // the member as comparable text (none: not compared, as paths)
  bool path = false;                          // the value may name a file (resolved against the file that set it)
};

// A member of a member struct (ModelSpec's unet.width is UNetOptions::width of ModelSpec::unet): a
// Choice whose reader and text reach s.*Outer.*Inner, so the inner struct is held whole and its
// defaults are its own. key_of finds its row by nested_member<Outer, Inner>'s reader.
template <auto Outer, auto Inner>
struct NestedMember {
  template <class S>
  static auto& of(S& s) {
    return (s.*Outer).*Inner;
  }
  template <class S>
  static void read(const Config& c, const std::string& key, S& s);
  template <class S>
  static std::string text(const S& s);
};

template <class S>
struct OptionField {
  const char* key;
  std::variant<double S::*, int64_t S::*, int S::*, uint64_t S::*, bool S::*, std::string S::*,
               std::filesystem::path S::*, Choice<S>>
      member;
  // Numbers only: the allowed range and what it means ("1 to 4096 filters"); no range when
  // `range` is empty. Text values are checked by their readers (an enhancer's name, a channel).
  double lo = -std::numeric_limits<double>::infinity();
  double hi = std::numeric_limits<double>::infinity();
  const char* range = "";
  const char* flag = "";  // the command-line flag that sets it ("lr" for --lr), where a command has one
};

// Several tables as one: a trainer's own rows after the rows it shares (the schedule).
template <class S>
std::vector<OptionField<S>> joined(std::vector<OptionField<S>> first, const std::vector<OptionField<S>>& second) {
  first.insert(first.end(), second.begin(), second.end());
  return first;
}

// The rows a table registers with the config (io/config.hpp), keys prefixed: each number's range,
// and each path-typed member as a path key (its value resolved against the file that set it).
template <class S>
std::vector<RangeRow> range_rows(const std::vector<OptionField<S>>& fields, const std::string& prefix = "") {
  std::vector<RangeRow> out;
  for (const auto& f : fields) {
    if (*f.range) out.push_back({prefix + f.key, f.lo, f.hi, f.range});
    const auto* choice = std::get_if<Choice<S>>(&f.member);
    if (std::holds_alternative<std::filesystem::path S::*>(f.member) || (choice && choice->path))
      out.push_back({prefix + f.key, 0, 0, "", /*path=*/true});
  }
  return out;
}

// The config key of the row that binds `member` (prefixed): what an error names instead of a
// key spelled again by hand. A member no row binds is a programming error.
template <class S, class T>
std::string key_of(const std::vector<OptionField<S>>& fields, T S::*member, const std::string& prefix = "") {
  for (const auto& f : fields)
    if (const auto* m = std::get_if<T S::*>(&f.member); m && *m == member) return prefix + f.key;
  throw std::logic_error("option table: no row binds this member");
}
// A member a struct inherits (a trainer's options extend the shared schedule).
template <class S, class T, class Base,
          std::enable_if_t<std::is_base_of_v<Base, S> && !std::is_same_v<Base, S>, int> = 0>
std::string key_of(const std::vector<OptionField<S>>& fields, T Base::*member, const std::string& prefix = "") {
  return key_of(fields, static_cast<T S::*>(member), prefix);
}

// A nested member's key (key_of for s.*Outer.*Inner): model_key's nested form calls this.
template <auto Outer, auto Inner, class S>
std::string nested_key_of(const std::vector<OptionField<S>>& fields, const std::string& prefix = "") {
  for (const auto& f : fields)
    if (const auto* c = std::get_if<Choice<S>>(&f.member);
        c && c->read == &NestedMember<Outer, Inner>::template read<S>)
      return prefix + f.key;
  throw std::logic_error("option table: no row binds this nested member");
}

// One member from its key (a missing key or a value of the wrong kind is an error naming the key).
template <class T>
void read_member(const Config& c, const std::string& key, T& member) {
  if constexpr (std::is_same_v<T, double>)
    member = c.num(key);
  else if constexpr (std::is_same_v<T, int64_t>)
    member = c.integer(key);
  else if constexpr (std::is_same_v<T, int>)
    member = static_cast<int>(c.integer(key));
  else if constexpr (std::is_same_v<T, uint64_t>)
    member = static_cast<uint64_t>(c.integer(key));
  else if constexpr (std::is_same_v<T, bool>)
    member = c.flag(key);
  else if constexpr (std::is_same_v<T, std::string>)
    member = c.str(key);
  else
    member = c.path(key);
}

template <auto Outer, auto Inner>
template <class S>
void NestedMember<Outer, Inner>::read(const Config& c, const std::string& key, S& s) {
  read_member(c, key, of(s));
}

// A member's value as the text a config holds: numbers exactly (a double to the digits that read back).
template <class T>
std::string member_text(const T& value) {
  if constexpr (std::is_same_v<T, bool>) {
    return value ? "true" : "false";
  } else if constexpr (std::is_integral_v<T>) {
    return std::to_string(value);
  } else if constexpr (std::is_floating_point_v<T>) {
    for (int digits = 6;; ++digits) {  // the shortest text that reads back (17 digits always do)
      std::ostringstream os;
      os << std::setprecision(digits) << value;
      if (digits >= 17 || std::strtod(os.str().c_str(), nullptr) == value) return os.str();
    }
  } else if constexpr (std::is_same_v<T, std::string>) {
    return value;
  } else {
    return value.string();  // a path
  }
}

template <auto Outer, auto Inner>
template <class S>
std::string NestedMember<Outer, Inner>::text(const S& s) {
  return member_text(of(s));
}

// The row binding s.*Outer.*Inner (a Choice<S>): {"unet.width", nested_member<&S::unet, &UNetOptions::width, S>()}.
template <auto Outer, auto Inner, class S>
Choice<S> nested_member() {
  return Choice<S>{&NestedMember<Outer, Inner>::template read<S>, &NestedMember<Outer, Inner>::template text<S>};
}

// Fills every field of `s` from `c`, each key read as `prefix` + its row's key (a missing key or a
// value of the wrong kind is an error naming the key).
template <class S>
void read_options(const Config& c, const std::vector<OptionField<S>>& fields, S& s, const std::string& prefix = "") {
  for (const auto& f : fields)
    std::visit(
        [&](auto member) {
          const auto key = prefix + f.key;
          if constexpr (std::is_same_v<decltype(member), Choice<S>>) {
            member.read(c, key, s);
          } else {
            read_member(c, key, s.*member);
          }
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
          const auto differs = [&](bool differ) {
            if (differ) out.push_back(prefix + f.key + ": the struct's default differs from " + c.str(prefix + f.key));
          };
          if constexpr (std::is_same_v<decltype(member), Choice<S>>) {
            if (member.text) differs(member.text(defaults) != member.text(from_config));
          } else {
            using T = std::decay_t<decltype(defaults.*member)>;
            if constexpr (!std::is_same_v<T, std::filesystem::path>)
              differs(!(defaults.*member == from_config.*member));
          }
        },
        f.member);
  return out;
}

}  // namespace flatnet
