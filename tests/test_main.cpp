#define CATCH_CONFIG_RUNNER
#include "catch_torch.hpp"

#include "core/util.hpp"
#include "train/options.hpp"

#include <cstdlib>
#include <string>

int main(int argc, char* argv[]) {
  // scripts/test.sh runs two test processes at once (ctest -j 2) and sets FLATNET_TEST_THREADS=1:
  // two processes of two OpenMP threads each on two cores spin-wait on each other (a 3 s test took 60 s).
  const char* threads = std::getenv("FLATNET_TEST_THREADS");
  flatnet::register_option_tables();
  flatnet::set_threads(threads ? std::atoi(threads) : 0);
  return Catch::Session().run(argc, argv);
}
