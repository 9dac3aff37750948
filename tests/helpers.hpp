#pragma once
// Shared test helpers: paths to fixtures and the shared data, a scratch folder, running the CLI.
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>

namespace test {

namespace fs = std::filesystem;

inline fs::path data_dir() { return FLATNET_TEST_DATA; }
inline fs::path source_dir() { return fs::path(FLATNET_TEST_DATA).parent_path().parent_path(); }
inline fs::path shared_dir() { return FLATNET_SHARED_DIR; }
inline fs::path rig_path() { return source_dir() / "models" / "camera" / "rig.mat"; }
inline fs::path calib_path() { return source_dir() / "models" / "camera" / "calib.mat"; }

// A fresh, empty folder under the system temp dir, removed at scope exit.
struct Scratch {
  fs::path dir;
  explicit Scratch(const std::string& name);
  ~Scratch();
};

struct RunResult {
  int code;
  std::string output;  // stdout and stderr together
};
// Runs the flatnet binary with the given argument string.
RunResult run_flatnet(const std::string& args);
// Runs a /bin/sh command line, stdout and stderr together.
RunResult run_shell(const std::string& command);

// Ends the running test as skipped. Under CTest (which sets FLATNET_CTEST) the process exits with
// code 77, which CTest reports as "Not Run (Skipped)", never as passed; run by hand it warns and
// returns. Use SKIP_TEST(why), which also returns from the test case, and tag the test [solo]: in
// a process shared with other test cases (tests/ctest_groups.hpp) a skip fails instead.
[[maybe_unused]] void skip(const std::string& why);
#define SKIP_TEST(why)          \
  do {                          \
    ::test::skip(why);          \
    WARN("skipped: " << (why)); \
    return;                     \
  } while (0)
// Whether /usr/bin/python3 has torch (the reference scripts' interpreter).
bool python_has_torch();

// Two photographs (the golden scenes) copied into `dir`, which is created; returns `dir`.
fs::path make_photos(const fs::path& dir);

// A file's bytes, written and read as they are (for hand-made hostile files).
inline void write_file(const fs::path& p, const std::string& bytes) {
  std::ofstream(p, std::ios::binary).write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}
inline std::string read_file(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

// A path quoted for a shell command line.
inline std::string q(const fs::path& p) { return "'" + p.string() + "'"; }

// The shipped recipes simulate their data on the fly from the shared photographs, with light
// augmentation; tests train them on a tiny dataset on disk instead (append to `flatnet train`).
inline const std::string kOnDisk =
    " --set data.source=dataset --set data.light.exposure_probability=0 --set data.light.lamp_probability=0";

}  // namespace test
