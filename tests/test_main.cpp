#define CATCH_CONFIG_RUNNER
#include "catch_torch.hpp"

#include "core/util.hpp"
#include "ctest_groups.hpp"
#include "train/options.hpp"

#include <cstdlib>
#include <iostream>
#include <set>
#include <string>

namespace {

// `flatnet_tests --list-groups`: the groups that hold at least one test case, one per line, for
// tests/add_ctest_groups.cmake to turn into CTest entries.
int list_groups(Catch::Session& session) {
  std::set<std::string> groups;
  for (const Catch::TestCase& test_case : Catch::getAllTestCasesSorted(session.config()))
    if (!test_case.isHidden() && !test::runs_alone(test_case))
      groups.insert(test::group_of(test_case.getTestCaseInfo()));
  for (const std::string& group : groups) std::cout << group << "\n";
  return 0;
}

}  // namespace

int main(int argc, char* argv[]) {
  // scripts/test.sh runs two test processes at once (ctest -j 2) and sets FLATNET_TEST_THREADS=1:
  // two processes of two OpenMP threads each on two cores spin-wait on each other (a 3 s test took 60 s).
  const char* threads = std::getenv("FLATNET_TEST_THREADS");
  flatnet::register_option_tables();
  flatnet::set_threads(threads ? std::atoi(threads) : 0);
  // The CLI's allocation policy (src/cli/main.cpp), so the library runs here as the commands run it:
  // freed tensors reused from the heap instead of mapped and page-faulted afresh (the reference
  // calibration's identification test 27 -> 17 s).
  flatnet::keep_freed_memory();
  Catch::Session session;
  if (argc == 2 && std::string(argv[1]) == "--list-groups") return list_groups(session);
  return session.run(argc, argv);
}
