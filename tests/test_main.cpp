#define CATCH_CONFIG_RUNNER
#include <catch2/catch.hpp>

#include "core/util.hpp"

int main(int argc, char* argv[]) {
  flatnet::set_threads(0);
  return Catch::Session().run(argc, argv);
}
