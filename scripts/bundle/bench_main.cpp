// `flatnet bench` alone, for scripts/bench_bundle.sh: the bench command without the commands that
// need OpenImageIO, Aravis or OpenCV's GUI, so that the bundle carries LibTorch's libraries only.
#include <exception>
#include <iostream>

#include "core/blas.hpp"

namespace flatnet::cli {
int bench(int argc, char** argv);
}

int main(int argc, char** argv) {
  flatnet::select_openblas_kernels(argv);
  try {
    return flatnet::cli::bench(argc, argv);
  } catch (const std::exception& e) {
    std::cerr << "flatnet bench: error: " << e.what() << "\n";
    return 2;
  }
}
