#pragma once
// `flatnet bench`: timings of the hot paths on this machine, the same rows that
// scripts/bench_reference.py times in Python PyTorch (scripts/bench_compare.sh prints the ratios).
// Each row: warm-up runs, then `repeats` timed runs; median and min in ms, and the peak resident
// memory of the row alone (the kernel's high-water mark is reset before each row).
#include <cmath>
#include <functional>
#include <string>
#include <vector>

#include "nn/generator.hpp"

namespace flatnet {

struct BenchOptions {
  int repeats = 5;
  int warmup = 1;
  InferenceLevers levers;       // for the infer_* rows (levers.bf16 is set from `bf16`)
  bool bf16 = false;            // infer_* with the enhancer in bf16, train_* with bf16 autocast
  int loader_workers = 2;       // for the loader row
  bool profile = false;         // one more run under LibTorch's profiler: BenchRow::ops
  bool profile_shapes = false;  // ... operators told apart by their input shapes and types
};

// One operator's share of a profiled run (LibTorch's profiler, CPU): self time excludes the
// operators it called, total includes them.
struct OpTime {
  std::string name;
  int64_t calls = 0;
  double self_ms = 0, total_ms = 0;
};

struct BenchRow {
  std::string name;
  std::string what;        // one line: the shapes and settings timed
  std::vector<double> ms;  // the timed runs
  double median_ms = 0, min_ms = 0;
  double peak_rss_mb = 0;   // VmHWM after the row (reset before it)
  double per_second = 0;    // derived throughput (items/s) where meaningful
  std::vector<OpTime> ops;  // with BenchOptions::profile: operators by self time, largest first
  // Floating-point work of one run in GFLOP (count_gflop: convolutions, matrix products and
  // elementwise arithmetic as LibTorch's profiler counts them, transposed convolutions and the
  // convolutions' backward from their shapes), NaN where not counted (FFTs, data loading).
  double gflop = std::nan("");
  double gflops() const { return gflop / (median_ms / 1e3); }  // achieved GFLOP/s (median run)
  // The precision whose practical peak this row is measured against ("fp32", "bf16"; empty: none):
  // the fastest of that precision's peak rows (GEMM or 3x3 convolution).
  std::string peak_kind;
};

// tikhonov, live_frame, simulator, infer_paper, infer_cpu, train_paper, train_cpu, train_recipe (the
// shipped models' GAN recipe), mask_step, loader
const std::vector<std::string>& bench_row_names();
// The machine's practical peak: peak_gemm_fp32, peak_conv_fp32, and (where the CPU runs bf16
// natively) peak_gemm_bf16, peak_conv_bf16. `flatnet bench --rows peak` runs them.
std::vector<std::string> peak_row_names();
// Rows whose cost depends on the precision (infer_*, train_*); in bf16 they are reported as NAME_bf16.
bool bench_row_has_precision(const std::string& name);
BenchRow run_bench_row(const std::string& name, const BenchOptions& options);

// GFLOP of one call of fn, counted by running it once under LibTorch's profiler with FLOP counting
// (aten::conv2d, mm, addmm, bmm, mul, add: 2 per multiply-add) plus, from their shapes, what the
// profiler does not count: aten::conv_transpose2d (2 N Cin H W Cout kh kw) and
// aten::convolution_backward (the input's and the weight's gradients, each the forward's work).
double count_gflop(const std::function<void()>& fn);

// Peak resident set size of this process in MB (VmHWM) and its reset (Linux /proc/self/clear_refs).
double peak_rss_mb();
void reset_peak_rss();

}  // namespace flatnet
