#pragma once
// How CTest runs the test cases (tests/add_ctest_groups.cmake). Each CTest entry is a process, and a
// process that links LibTorch takes about a second to start (docs/results/performance.md), so the
// short test cases of one source file share one process: its group, "unit:<file>". A test case runs
// in a process of its own when it is tagged
//   [slow]  the slow label's end-to-end runs, or
//   [solo]  a test that can skip (SKIP_TEST ends its process with exit 77, which would end the rest
//           of a group and report them all as skipped), or one long enough to want a core of its own.
// Hidden test cases ([.]) belong to no entry: they run only when named.
#include "catch_torch.hpp"

#include <string>

namespace test {

inline bool runs_alone(const Catch::TestCaseInfo& info) {
  for (const std::string& tag : info.lcaseTags)
    if (tag == "slow" || tag == "solo") return true;
  return false;
}

// The group a test case shares a process with: its source file's name without the extension (the
// tag Catch2's -# option gives it, "[#test_io]").
inline std::string group_of(const Catch::TestCaseInfo& info) {
  std::string file = info.lineInfo.file;
  file = file.substr(file.find_last_of('/') + 1);
  return file.substr(0, file.find_last_of('.'));
}

}  // namespace test
