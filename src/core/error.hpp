#pragma once
// Errors flatnet reports to its user. Every user-facing failure is an flatnet::Error that names
// the file (or option) and what is wrong; `main` prints it on one line and exits with code 2.
//
// Options inside an error's text are marked, not spelled: library layers know an option by its
// key (`simulate.lamp_gain`, SimulateOptions::lamp_gain), a command-line user by its flag
// (`--lamp-gain`). `option_key(key)` marks a key; what() shows it as the key, and a front end
// renders each mark its own way (Error::render; the CLI: the flag it registered for that key),
// never by searching the text for names.
#include <filesystem>
#include <functional>
#include <stdexcept>
#include <string>

namespace flatnet {

inline constexpr char kOptionMark = '\x1e';  // ASCII record separator: brackets a marked key

// `key` marked as an option inside an error's text.
inline std::string option_key(const std::string& key) { return kOptionMark + key + kOptionMark; }

// `text` (user data: a file name, a value) with any mark shown as the escape `\x1e`, so that nothing a
// user wrote is ever rendered as an option.
inline std::string unmarked(const std::string& text) {
  std::string out;
  for (const char c : text) out += c == kOptionMark ? std::string("\\x1e") : std::string(1, c);
  return out;
}

// `marked` with each marked key replaced by name(key) (the key itself when `name` is empty).
inline std::string render_option_keys(const std::string& marked,
                                      const std::function<std::string(const std::string&)>& name = {}) {
  std::string out;
  for (size_t at = 0; at < marked.size();) {
    const size_t open = marked.find(kOptionMark, at);
    const size_t close = open == std::string::npos ? std::string::npos : marked.find(kOptionMark, open + 1);
    if (close == std::string::npos) return out + marked.substr(at);  // an unpaired mark is text
    const auto key = marked.substr(open + 1, close - open - 1);
    out += marked.substr(at, open - at) + (name ? name(key) : key);
    at = close + 1;
  }
  return out;
}

class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& what) : std::runtime_error(render_option_keys(what)), marked_(what) {}
  // "<where>: <reason>". A label the code wrote (a command, a flag, a marked key) comes as text; a
  // file comes as a path, and a path is the user's data: a mark inside its name shows escaped.
  Error(const std::string& where, const std::string& reason) : Error(where + ": " + reason) {}
  Error(const char* where, const std::string& reason) : Error(std::string(where) + ": " + reason) {}
  Error(const std::filesystem::path& where, const std::string& reason)
      : Error(unmarked(where.string()) + ": " + reason) {}
  // The message with each marked option shown as name(key).
  std::string render(const std::function<std::string(const std::string&)>& name) const {
    return render_option_keys(marked_, name);
  }

 private:
  std::string marked_;
};

// Throws Error(where, reason) unless cond holds (where: a file, or a label the code wrote).
inline void require(bool cond, const std::filesystem::path& where, const std::string& reason) {
  if (!cond) throw Error(where, reason);
}
inline void require(bool cond, const std::string& where, const std::string& reason) {
  if (!cond) throw Error(where, reason);
}
inline void require(bool cond, const char* where, const std::string& reason) {
  if (!cond) throw Error(where, reason);
}

// An error about one option, named first (marked): "<key>: <reason>".
inline void require_option(bool cond, const std::string& key, const std::string& reason) {
  if (!cond) throw Error(option_key(key) + ": " + reason);
}

}  // namespace flatnet
