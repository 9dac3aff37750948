#pragma once
// Every command's flags from rows (issue 91): one declaration per setting. A row binds a flag to a
// member of the command's options struct and carries the setting's one doc text and, for a number,
// its range; the default is the struct's own (S{}), shown by --help and by `flatnet options --for
// COMMAND`, and never written a second time. A flag the user leaves out leaves the member as the
// struct has it. The trainers' settings keep their config rows (io/option_table.hpp), whose docs
// live in their defaults files; these rows are for the settings a command alone reads.
#include <cmath>
#include <cxxopts.hpp>
#include <filesystem>
#include <functional>
#include <limits>
#include <map>
#include <sstream>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <variant>
#include <vector>

#include "core/error.hpp"
#include "core/util.hpp"

// GCC 12 instantiates every member type of a row's variant for every struct and warns of reading a
// std::string out of a 4-byte struct on paths that never run (-Warray-bounds), and of a struct's
// defaults "maybe uninitialized": false positives.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Warray-bounds"
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"

namespace flatnet::cli {

// A setting its own functions read and show (an enum's name, on|off, a list).
template <class S>
struct FlagText {
  // Throws std::invalid_argument(what is wrong) on a bad text, shown after the flag; a library
  // reader's Error (which names its option key, shown as the flag) passes as it is.
  void (*set)(S& s, const std::string& text);
  std::string (*get)(const S& s);
};

template <class S>
struct FlagRow {
  using Struct = S;
  const char* flag;  // "val-fraction" for --val-fraction
  // A bool is a switch (given: true; its struct default must be false); a list of texts is a
  // repeatable flag (each occurrence whole, in order: a value may hold commas).
  std::variant<double S::*, int64_t S::*, int S::*, uint64_t S::*, bool S::*, std::string S::*,
               std::filesystem::path S::*, std::vector<std::string> S::*, FlagText<S>>
      member;
  const char* doc;
  // Numbers only: the allowed range and what it means ("0 to 1"); none when `range` is empty.
  double lo = -std::numeric_limits<double>::infinity();
  double hi = std::numeric_limits<double>::infinity();
  const char* range = "";
};

template <class S>
using FlagTable = std::vector<FlagRow<S>>;

// A comma list (A,B,...) as its items, each whole; an empty item is kept (two commas together, a
// trailing comma), for the reader to name.
inline std::vector<std::string> comma_items(const std::string& text) {
  std::vector<std::string> items;
  size_t start = 0;
  for (size_t comma = text.find(','); comma != std::string::npos; comma = text.find(',', start)) {
    items.push_back(text.substr(start, comma - start));
    start = comma + 1;
  }
  if (!text.empty()) items.push_back(text.substr(start));
  return items;
}

// A row's reader for a comma-list flag (--models A,B,...) into a list member.
template <class S, std::vector<std::string> S::*member>
FlagText<S> comma_list() {
  return {[](S& s, const std::string& text) { s.*member = comma_items(text); },
          [](const S& s) {
            std::string text;
            for (const auto& item : s.*member) text += (text.empty() ? "" : ",") + item;
            return text;
          }};
}

// What `flatnet options --for COMMAND` prints of a row.
struct FlagDescription {
  std::string flag, default_text, range, doc;
  bool is_switch = false;
};

namespace flag_detail {

template <class T>
std::string shown(const T& value) {
  if constexpr (std::is_same_v<T, std::string>) {
    return value;
  } else if constexpr (std::is_same_v<T, std::filesystem::path>) {
    return value.string();
  } else if constexpr (std::is_same_v<T, bool>) {
    return value ? "true" : "false";
  } else if constexpr (std::is_same_v<T, std::vector<std::string>>) {
    std::string joined;
    for (const auto& v : value) joined += (joined.empty() ? "" : " ") + v;
    return joined;
  } else {
    std::ostringstream s;
    s.precision(10);
    s << value;
    return s.str();
  }
}

// A row's member in `s` as text.
template <class S>
std::string value_text(const FlagRow<S>& row, const S& s) {
  return std::visit(
      [&](auto member) -> std::string {
        if constexpr (std::is_same_v<decltype(member), FlagText<S>>) {
          return member.get(s);
        } else {
          return shown(s.*member);
        }
      },
      row.member);
}

template <class S>
bool is_switch(const FlagRow<S>& row) {
  return std::holds_alternative<bool S::*>(row.member);
}

// The given text into the member; errors name the flag and say what is wrong.
template <class T>
void assign_number(const std::string& flag, const std::string& text, double lo, double hi, const char* range,
                   T& member) {
  const NumberRule rule{flag.c_str(), lo, hi, *range ? range : std::is_integral_v<T> ? "a whole number" : "a number"};
  const auto problem = number_problem(text, rule);
  if (!problem.empty()) throw Error("--" + flag, "'" + printable(text) + "' " + problem + ": " + rule.meaning);
  const double value = std::strtod(text.c_str(), nullptr);  // std::stod throws on a subnormal (1e-320)
  if constexpr (std::is_integral_v<T>) {
    if constexpr (std::is_unsigned_v<T>) {
      if (value < 0) throw Error("--" + flag, "'" + printable(text) + "' is negative");
    }
    // 2^63 and 2^64 are exact doubles; the cast below is defined only inside the type's range.
    if (value < static_cast<double>(std::numeric_limits<T>::lowest()) ||
        value >= std::ldexp(1.0, std::numeric_limits<T>::digits))
      throw Error("--" + flag, "'" + printable(text) + "' is out of range for this setting");
    if (value != std::floor(value)) throw Error("--" + flag, "'" + printable(text) + "' is not a whole number");
  }
  member = static_cast<T>(value);
}

}  // namespace flag_detail

// Declares each row's flag: a switch for a bool, else a value whose help ends with the struct's
// default (and the range, where the row has one).
template <class S>
void add_flags(cxxopts::Options& options, const FlagTable<S>& rows, const std::string& group = "") {
  static const S defaults{};
  for (const auto& row : rows) {
    if (flag_detail::is_switch(row)) {
      if (defaults.*std::get<bool S::*>(row.member))
        throw std::logic_error(std::string("flag rows: the switch --") + row.flag + " defaults to true");
      options.add_options(group)(row.flag, row.doc);
      continue;
    }
    std::string help = row.doc;
    const auto value = flag_detail::value_text(row, defaults);
    if (!value.empty()) help += " (default: " + value + ")";
    if (*row.range) help += " [" + std::string(row.range) + "]";
    options.add_options(group)(row.flag, help, cxxopts::value<std::string>());
  }
}

// Fills `s` from the flags the user gave; the others keep `s`'s values. A number is checked
// against its row's range, a text by its reader; errors name the flag.
template <class S>
void read_flags(const cxxopts::ParseResult& r, const FlagTable<S>& rows, S& s) {
  for (const auto& row : rows) {
    if (!r.count(row.flag)) continue;
    if (flag_detail::is_switch(row)) {
      s.*std::get<bool S::*>(row.member) = true;
      continue;
    }
    if (const auto* list = std::get_if<std::vector<std::string> S::*>(&row.member)) {
      for (const auto& kv : r.arguments())
        if (kv.key() == row.flag) (s.**list).push_back(kv.value());
      continue;
    }
    const auto text = r[row.flag].template as<std::string>();
    std::visit(
        [&](auto member) {
          using M = decltype(member);
          if constexpr (std::is_same_v<M, FlagText<S>>) {
            try {
              member.set(s, text);
            } catch (const std::invalid_argument& e) {
              throw Error("--" + std::string(row.flag), "'" + printable(text) + "': " + e.what());
            }
          } else {
            using T = std::decay_t<decltype(s.*member)>;
            if constexpr (std::is_same_v<T, std::string> || std::is_same_v<T, std::filesystem::path>) {
              s.*member = T(text);
            } else if constexpr (!std::is_same_v<T, bool> && !std::is_same_v<T, std::vector<std::string>>) {
              flag_detail::assign_number(row.flag, text, row.lo, row.hi, row.range, s.*member);
            }
          }
        },
        row.member);
  }
}

template <class S>
std::vector<FlagDescription> describe_flags(const FlagTable<S>& rows) {
  static const S defaults{};
  std::vector<FlagDescription> out;
  for (const auto& row : rows)
    out.push_back({row.flag, flag_detail::value_text(row, defaults), row.range, row.doc, flag_detail::is_switch(row)});
  return out;
}

// A command's flag tables, type-erased: what `flatnet options --for COMMAND` prints and what a test
// holds to the structs (every row's value after parsing `args`, keyed by flag).
struct CommandFlags {
  std::string command;  // "simulate", "eval fit-niqe"
  std::function<std::vector<FlagDescription>()> describe;
  std::function<std::map<std::string, std::string>(const std::vector<std::string>& args)> parse;
};

// Builds a CommandFlags from one or more tables over their structs.
template <class... S>
CommandFlags command_flags(std::string command, const FlagTable<S>&... tables) {
  CommandFlags c;
  c.command = std::move(command);
  c.describe = [&tables...]() {
    std::vector<FlagDescription> out;
    (
        [&](const auto& table) {
          const auto d = describe_flags(table);
          out.insert(out.end(), d.begin(), d.end());
        }(tables),
        ...);
    return out;
  };
  c.parse = [&tables...](const std::vector<std::string>& args) {
    cxxopts::Options options("flag rows");
    (add_flags(options, tables), ...);
    std::vector<std::string> all = {"flatnet"};
    all.insert(all.end(), args.begin(), args.end());
    std::vector<char*> argv;
    for (auto& a : all) argv.push_back(a.data());
    const auto r = options.parse(static_cast<int>(argv.size()), argv.data());
    std::map<std::string, std::string> values;
    (
        [&](const auto& table) {
          typename std::decay_t<decltype(table)>::value_type::Struct s{};
          read_flags(r, table, s);
          for (const auto& row : table) values[row.flag] = flag_detail::value_text(row, s);
        }(tables),
        ...);
    return values;
  };
  return c;
}

}  // namespace flatnet::cli

#pragma GCC diagnostic pop
