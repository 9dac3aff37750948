#include "core/blas.hpp"

#include <cstdlib>
#if defined(__linux__)
#include <unistd.h>
#endif

// OpenBLAS's own query; weak, so that a program running on another BLAS still starts (null then).
extern "C" char* openblas_get_corename(void) __attribute__((weak));

namespace flatnet {

namespace {
constexpr const char* kChoseVariable = "FLATNET_OPENBLAS_CHOSE";
}

std::string openblas_core() {
  if (openblas_get_corename == nullptr) return "";
  const char* name = openblas_get_corename();
  return name ? name : "";
}

std::string better_openblas_core(const std::string& current, const CpuFeatures& cpu, const char* user_choice) {
  if (user_choice != nullptr && *user_choice != '\0') return "";
  if (current.empty()) return "";
  // Under oneDNN's ISA cap (ONEDNN_MAX_CPU_ISA=AVX2) the whole process behaves as the AVX2 kind:
  // OpenBLAS, which does not read that cap, gets its AVX2 kernels too, whatever it chose. A CPU it
  // predates gets its SSE3 fallback "Prescott" (Emerald Rapids on 0.3.21), which the cap must not keep.
  const bool avx2_kernels = current == "Haswell" || current == "Zen";
  if (!cpu.avx512_core) return cpu.onednn_capped && !avx2_kernels ? "Haswell" : "";
  if (current == "SkylakeX" || current == "SapphireRapids") return "";
  return "SkylakeX";
}

void select_openblas_kernels(char** argv) {
#if defined(__linux__)
  const char* user_choice = std::getenv("OPENBLAS_CORETYPE");
  if (user_choice != nullptr && *user_choice != '\0') return;  // the user's choice: nothing to read or decide
  const std::string current = openblas_core();
  if (current.empty()) return;  // not OpenBLAS
  const std::string wanted = better_openblas_core(current, cpu_features(), user_choice);
  if (wanted.empty()) return;
  setenv("OPENBLAS_CORETYPE", wanted.c_str(), 1);
  setenv(kChoseVariable, current.c_str(), 1);
  execv("/proc/self/exe", argv);
  unsetenv("OPENBLAS_CORETYPE");  // exec failed: run on with the library's choice
  unsetenv(kChoseVariable);
#else
  (void)argv;
#endif
}

std::string describe_blas() {
  const std::string core = openblas_core();
  if (core.empty()) return "not OpenBLAS";
  std::string text = "OpenBLAS " + core;
  const char* chose = std::getenv(kChoseVariable);
  if (chose != nullptr && *chose != '\0') text += std::string(" (set by flatnet; OpenBLAS chose ") + chose + ")";
  return text;
}

}  // namespace flatnet
