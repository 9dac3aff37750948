#pragma once
// A parser of outside bytes that was not written for hostile input, run where its failures cannot
// reach flatnet: a child process (fork) that, once it has opened its file, may only compute, allocate
// and write to a pipe (a seccomp filter refuses every other system call), under a CPU-time and a
// wall-clock limit. HDF5 is such a parser: scripts/fuzz.sh found heap overflows and wild reads in
// Debian 12's libhdf5 1.10.8 reading damaged v7.3 .mat files (issue 113). A crash, a hang or an
// exploit of the parser ends in the child, and the parent reports the file as damaged.
#include <cstdint>
#include <filesystem>
#include <functional>
#include <string>

namespace flatnet {

struct IsolatedReadOptions {
  uint64_t max_output_bytes = 1ull << 30;  // what the parent accepts from the child
  uint64_t max_memory_bytes = 4ull << 30;  // the child's address space beyond the parent's (not under ASan)
  int cpu_seconds = 60;
  int wall_seconds = 120;
  std::string reader = "its reader";  // how errors name the parser: "its HDF5 (v7.3) reader"
};

// What the child runs: open the file, call `lock_down()` (from then on no file can be opened, no
// process started, no socket made), parse, and return the bytes to hand back. An exception's text
// comes back as an Error; a crash, a signal or a limit comes back as "<file>: ... (a damaged file?)".
using IsolatedParse = std::function<std::string(const std::function<void()>& lock_down)>;

std::string read_isolated(const std::filesystem::path& path, const IsolatedParse& parse,
                          const IsolatedReadOptions& options = {});

}  // namespace flatnet
