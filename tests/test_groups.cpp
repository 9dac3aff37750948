// How CTest runs the suite (tests/ctest_groups.hpp): the short test cases of a file share a
// process, and a test that can skip runs alone, so that a skip never hides its neighbours.
#include "catch_torch.hpp"

#include <fstream>
#include <sstream>

#include "ctest_groups.hpp"
#include "helpers.hpp"

namespace {

// The source of a test case: from its TEST_CASE line to the next one (or the file's end).
std::string source_of(const Catch::TestCaseInfo& info) {
  std::ifstream in(info.lineInfo.file);
  REQUIRE(in);
  const std::string next_case = std::string("TEST_CASE") + "(";  // spelt so that CMake's name check skips it
  std::string text, line;
  for (std::size_t n = 1; std::getline(in, line); ++n) {
    if (n < info.lineInfo.line) continue;
    if (n > info.lineInfo.line && line.find(next_case) != std::string::npos) break;
    text += line + "\n";
  }
  return text;
}

}  // namespace

TEST_CASE("every test case that can skip runs in a process of its own ([solo] or [slow])", "[suite]") {
  const auto& all = Catch::getAllTestCasesSorted(*Catch::getCurrentContext().getConfig());
  const std::string skip_call = std::string("SKIP_TEST") + "(";  // spelt so that this test's own source does not match
  int can_skip = 0;
  for (const Catch::TestCase& test_case : all) {
    if (test_case.isHidden() || source_of(test_case).find(skip_call) == std::string::npos) continue;
    ++can_skip;
    INFO(test_case.name << " (" << test_case.lineInfo.file << ":" << test_case.lineInfo.line << ")");
    CHECK(test::runs_alone(test_case));
  }
  CHECK(can_skip >= 20);  // the scan finds the skipping tests there are (at least those of 2026-12)
}

// A test that always skips, run only by name (hidden by [.]), for the protocol's test below.
TEST_CASE("skip probe", "[.][skip_probe]") { SKIP_TEST("the probe always skips"); }

TEST_CASE("a skip: exit 77 in its own process, a failure naming [solo] in a shared one", "[suite]") {
  const std::string tests = std::filesystem::read_symlink("/proc/self/exe").string();
  auto alone = test::run_shell("env -u FLATNET_CTEST_GROUP FLATNET_CTEST=1 " + test::q(tests) + " '[skip_probe]'");
  INFO(alone.output);
  CHECK(alone.code == 77);
  CHECK_THAT(alone.output, Catch::Contains("skipped: the probe always skips"));
  auto shared = test::run_shell("env FLATNET_CTEST=1 FLATNET_CTEST_GROUP=1 " + test::q(tests) + " '[skip_probe]'");
  INFO(shared.output);
  CHECK(shared.code == 1);
  CHECK_THAT(shared.output, Catch::Contains("tag it [solo]"));
  // By hand (no CTest), a skip warns and the run goes on.
  auto by_hand = test::run_shell("env -u FLATNET_CTEST -u FLATNET_CTEST_GROUP " + test::q(tests) + " '[skip_probe]'");
  INFO(by_hand.output);
  CHECK(by_hand.code == 0);
  CHECK_THAT(by_hand.output, Catch::Contains("skipped: the probe always skips"));
}

TEST_CASE("flatnet_tests --list-groups names each source file whose short test cases share a process", "[suite]") {
  const std::string tests = std::filesystem::read_symlink("/proc/self/exe").string();
  const auto r = test::run_shell("env -u FLATNET_CTEST_GROUP " + test::q(tests) + " --list-groups");
  INFO(r.output);
  REQUIRE(r.code == 0);
  CHECK_THAT(r.output, Catch::Contains("test_groups\n") && Catch::Contains("test_io\n"));
  CHECK_THAT(r.output, !Catch::Contains("test_main"));  // it holds no test case
  std::istringstream lines(r.output);
  int groups = 0;
  for (std::string group; std::getline(lines, group); ++groups) {
    INFO(group);
    CHECK(std::filesystem::is_regular_file(test::source_dir() / "tests" / (group + ".cpp")));
  }
  CHECK(groups >= 30);
}
