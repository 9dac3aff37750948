#include "helpers.hpp"

#include <unistd.h>

#include <array>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <sys/wait.h>

namespace test {

Scratch::Scratch(const std::string& name) {
  dir = fs::temp_directory_path() / ("flatnet_test_" + name + "_" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
}

Scratch::~Scratch() {
  std::error_code ec;
  fs::remove_all(dir, ec);
}

RunResult run_flatnet(const std::string& args) { return run_shell(std::string(FLATNET_BINARY) + " " + args); }

RunResult run_shell(const std::string& command) {
  const std::string cmd = command + " 2>&1";
  FILE* pipe = ::popen(cmd.c_str(), "r");
  std::string out;
  std::array<char, 4096> buf{};
  while (pipe && std::fgets(buf.data(), buf.size(), pipe)) out += buf.data();
  const int status = pipe ? ::pclose(pipe) : -1;
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, out};
}

}  // namespace test

namespace test {

void skip(const std::string& why) {
  if (std::getenv("FLATNET_CTEST") == nullptr) return;
  if (std::getenv("FLATNET_CTEST_GROUP") != nullptr) {
    // Exit 77 here would report the group's other test cases as skipped too (tests/ctest_groups.hpp).
    std::printf("this test skips (%s) but shares its process with others: tag it [solo]\n", why.c_str());
    std::fflush(stdout);
    std::_Exit(1);
  }
  std::printf("skipped: %s\n", why.c_str());
  std::fflush(stdout);
  std::_Exit(77);
}

bool python_has_torch() {
  static const bool has = std::system("/usr/bin/python3 -c 'import torch' >/dev/null 2>&1") == 0;
  return has;
}

fs::path make_photos(const fs::path& dir) {
  fs::create_directories(dir);
  for (const char* n : {"bsds_16052_scene.png", "inet_n02980441_castle_scene.png"})
    fs::copy_file(data_dir() / "golden" / n, dir / n);
  return dir;
}

}  // namespace test
