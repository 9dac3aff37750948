#pragma once
// OpenBLAS (what LibTorch's fp32 torch::mm/bmm call) picks its kernels by CPU model when it loads.
// Debian 12's 0.3.21 predates recent CPUs and falls back badly on them (flatnet bench --rows
// peak_gemm_fp32, GEMM 2048^3): on an Intel Xeon of model 207 (Emerald Rapids) it takes the generic
// "Prescott" SSE3 kernels, 41 GFLOP/s on two cores where its SkylakeX kernels give 233; on an AMD
// EPYC of family 26 (Zen 5) it takes "Cooperlake", 153 GFLOP/s on one core against SkylakeX's 244.
// OPENBLAS_CORETYPE overrides the choice, but only when set before the library loads, so the CLI
// re-executes itself once with it set (select_openblas_kernels). A user's own OPENBLAS_CORETYPE wins.
#include <string>

#include "core/precision.hpp"

namespace flatnet {

// The kernel set OpenBLAS chose ("SkylakeX", "Prescott"...), or "" where the BLAS is not OpenBLAS.
std::string openblas_core();

// The OpenBLAS core to ask for instead of `current`, or "" to keep it: SkylakeX on CPUs with
// AVX-512 (F, CD, BW, DQ, VL) where OpenBLAS chose anything but SkylakeX or its own newer
// SapphireRapids; Haswell where oneDNN is capped below AVX-512 (the AVX2 kind, whole process) and
// OpenBLAS chose another set than Haswell or Zen;
// "" when `user_choice` (OPENBLAS_CORETYPE) is set or the BLAS is not OpenBLAS.
std::string better_openblas_core(const std::string& current, const CpuFeatures& cpu, const char* user_choice);

// Re-executes this program (/proc/self/exe, the same argv) with OPENBLAS_CORETYPE set where
// better_openblas_core asks for it, recording the library's own choice in FLATNET_OPENBLAS_CHOSE.
// Returns where nothing is to be done or the re-execution failed (the program then runs as it is).
void select_openblas_kernels(char** argv);

// "OpenBLAS SkylakeX (set by flatnet; OpenBLAS chose Prescott)", "OpenBLAS Haswell", "not OpenBLAS".
std::string describe_blas();

}  // namespace flatnet
