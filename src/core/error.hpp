#pragma once
// Errors flatnet reports to its user. Every user-facing failure is an flatnet::Error that names
// the file (or option) and what is wrong; `main` prints it on one line and exits with code 2.
#include <filesystem>
#include <stdexcept>
#include <string>

namespace flatnet {

class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& what) : std::runtime_error(what) {}
  // "<path>: <reason>"
  Error(const std::filesystem::path& where, const std::string& reason)
      : std::runtime_error(where.string() + ": " + reason) {}
};

// Throws Error(where, reason) unless cond holds.
inline void require(bool cond, const std::filesystem::path& where, const std::string& reason) {
  if (!cond) throw Error(where, reason);
}

}  // namespace flatnet
