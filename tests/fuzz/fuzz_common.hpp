#pragma once
// What every libFuzzer harness shares (scripts/fuzz.sh builds and runs them). A reader given bytes
// from outside may refuse them only with a flatnet::Error, the error a user sees with the file named.
// Anything else is a finding: a sanitizer report (ASan, UBSan), a crash, an allocation past
// libFuzzer's -rss_limit_mb / -malloc_limit_mb, a hang past -timeout, or another exception (which
// the CLI would print as "internal error"), reported here with its message and then abort().
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <fstream>
#include <functional>
#include <string>

#include "core/error.hpp"
#include "nn/model_spec.hpp"

namespace flatnet::fuzz {

// The input as a file named `name` in a folder of this process's own (readers take paths, and some,
// like OpenImageIO's, choose their format by the extension).
inline std::filesystem::path as_file(const uint8_t* data, size_t size, const std::string& name) {
  static const auto dir = [] {
    const char* tmp = std::getenv("TMPDIR");
    auto d = std::filesystem::path(tmp ? tmp : "/tmp") / ("flatnet-fuzz-" + std::to_string(::getpid()));
    std::filesystem::create_directories(d);
    return d;
  }();
  const auto path = dir / name;
  std::ofstream(path, std::ios::binary | std::ios::trunc).write(reinterpret_cast<const char*>(data), size);
  return path;
}

// Runs one read; a flatnet::Error is the reader's correct refusal. The model's option ranges are
// registered first, as the CLI's main does (a config's numbers are checked against them).
inline void expect_clean(const std::function<void()>& read) {
  register_model_option_tables();
  try {
    read();
  } catch (const flatnet::Error&) {
  } catch (const std::exception& e) {
    std::fprintf(stderr, "fuzz finding: an exception that is not a flatnet::Error reached the caller: %s\n", e.what());
    std::abort();
  }
}

}  // namespace flatnet::fuzz
