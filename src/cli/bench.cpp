#include <fstream>
#include <iomanip>
#include <iostream>
#include <map>

#include <nlohmann/json.hpp>

#include "cli/commands.hpp"
#include "core/blas.hpp"
#include "core/error.hpp"
#include "core/precision.hpp"
#include "core/util.hpp"
#include "bench/bench.hpp"
#include "eval/tables.hpp"  // fixed: "-" for NaN

namespace flatnet::cli {

namespace {

void print_profile(const BenchRow& row, int top) {
  double all_self = 0;
  for (const auto& op : row.ops) all_self += op.self_ms;
  std::cout << "  profile of one more run (" << std::fixed << std::setprecision(1) << all_self
            << " ms of operators):\n  " << std::setw(10) << "self ms" << std::setw(8) << "self %" << std::setw(11)
            << "total ms" << std::setw(7) << "calls"
            << "  operator\n";
  for (int i = 0; i < std::min<int>(top, row.ops.size()); ++i) {
    const auto& op = row.ops[i];
    std::cout << "  " << std::setw(10) << op.self_ms << std::setw(8)
              << (all_self > 0 ? 100.0 * op.self_ms / all_self : 0.0) << std::setw(11) << op.total_ms << std::setw(7)
              << op.calls << "  " << op.name << "\n";
  }
  std::cout << std::flush;
}

// --rows as a list ("peak" expands to the peak rows; empty: every row), the peak rows first so that
// every other row can be given its share of the peak.
std::vector<std::string> rows_to_run(const std::string& list) {
  std::vector<std::string> rows;
  if (list.empty()) {
    rows = bench_row_names();
  } else {
    std::stringstream in(list);
    for (std::string item; std::getline(in, item, ',');) {
      if (item != "peak") {
        rows.push_back(item);
        continue;
      }
      for (const auto& p : peak_row_names()) rows.push_back(p);
    }
  }
  std::stable_partition(rows.begin(), rows.end(), [](const std::string& n) { return n.rfind("peak_", 0) == 0; });
  return rows;
}

void print_row(const BenchRow& row, double gflops, double share) {
  std::cout << std::left << std::setw(15) << row.name << std::right << std::fixed << std::setprecision(2)
            << std::setw(10) << row.median_ms << std::setw(12) << row.min_ms << std::setprecision(0) << std::setw(12)
            << row.peak_rss_mb << std::setprecision(2) << std::setw(12) << row.per_second << std::setw(10)
            << fixed(gflops, 1) << std::setw(8) << fixed(100 * share, 1) << "  " << row.what << std::endl;
}

nlohmann::json row_json(const BenchRow& row, double gflops, double share) {
  auto number = [](double v) { return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr); };
  return {{"name", row.name},
          {"what", row.what},
          {"median_ms", row.median_ms},
          {"min_ms", row.min_ms},
          {"runs_ms", row.ms},
          {"peak_rss_mb", row.peak_rss_mb},
          {"per_second", row.per_second},
          {"gflop", number(row.gflop)},
          {"gflops", number(gflops)},
          {"peak_kind", row.peak_kind},
          {"peak_share", number(share)}};
}

}  // namespace

namespace {

// bench's settings: the library's options with which rows to run and where the results go.
struct BenchSettings : BenchOptions {
  std::string rows;
  std::filesystem::path json;
  int profile_top = 0;
};

const FlagTable<BenchSettings>& bench_flags() {
  using S = BenchSettings;
  static const FlagTable<S> rows = {
      {"rows", &S::rows,
       "comma list of rows (default: all; peak: the machine's practical peak rows, which then give every row its "
       "share of the peak)"},
      {"json", &S::json, "also write the results to this JSON file"},
      {"profile", &S::profile_top,
       "after each row, one more run under LibTorch's profiler (after one that warms it up); print its N costliest "
       "operators by self time (and all of them into --json)",
       0, 1e6, "0 (no profile) or more operators"},
      {"profile-shapes", static_cast<bool S::*>(&BenchOptions::profile_shapes),
       "with --profile: tell operators apart by input shapes and types"},
      {"repeats", static_cast<int S::*>(&BenchOptions::repeats), "timed runs per row", 1, 1e6, "at least 1"},
      {"warmup", static_cast<int S::*>(&BenchOptions::warmup), "untimed runs before them", 0, 1e6, "0 or more"},
      {"levers",
       FlagText<S>{[](S& s, const std::string& text) { set_levers_of<BenchOptions, &BenchOptions::levers>(s, text); },
                   [](const S& s) { return levers_text_of<BenchOptions, &BenchOptions::levers>(s); }},
       "inference levers for infer_*: none, or a list of fold, channels-last, gemm-up, bf16, onednn (onednn: with "
       "bf16)"},
  };
  return rows;
}

const FlagTable<PrecisionChoice>& bench_precision_flags() {
  static const FlagTable<PrecisionChoice> rows = {
      {"precision", &PrecisionChoice::precision,
       "auto|fp32|bf16|both: precision of the infer_* and train_* rows (both: each row twice, the bf16 one named "
       "ROW_bf16); auto is bf16 where the CPU has it natively"},
  };
  return rows;
}

}  // namespace

CommandFlags bench_command_flags() { return command_flags("bench", bench_flags(), bench_precision_flags()); }

int bench(int argc, char** argv) {
  cxxopts::Options o("flatnet bench",
                     "Time the hot paths (median and min of N runs after warm-up, peak memory per row).\n"
                     "scripts/bench_compare.sh runs these rows beside their Python PyTorch twins.");
  add_flags(o, bench_flags());
  add_flags(o, bench_precision_flags());
  add_common(o);
  cxxopts::ParseResult r;
  if (!parse(o, argc, argv, r)) return 0;
  BenchSettings settings;
  read_flags(r, bench_flags(), settings);
  BenchOptions opt = settings;
  PrecisionChoice chosen;
  read_flags(r, bench_precision_flags(), chosen);
  const int profile_top = settings.profile_top;
  opt.profile = r.count("profile") > 0;
  if (r.count("json"))  // its folder made (as the writer would) before the rows run, not after minutes of them
    std::filesystem::create_directories(std::filesystem::absolute(settings.json).parent_path());
  require(!opt.profile_shapes || opt.profile, "bench", "--profile-shapes goes with --profile N");
  const auto rows = rows_to_run(settings.rows);
  const auto choice = chosen.precision;
  std::vector<bool> precisions;  // bf16 or not, per pass over a precision-dependent row
  if (choice == "both")
    precisions = {false, true};
  else
    precisions = {resolve_precision(choice, "--precision") == Precision::bf16};
  if (precisions.back()) request_amx_permission();
  const int threads = at::get_num_threads();
  const auto& cpu = cpu_features();
  std::cout << "flatnet bench: " << threads << " threads, " << opt.repeats << " runs after " << opt.warmup
            << " warm-up\n"
            << "cpu: " << cpu.summary() << "; bf16: " << cpu.bf16_engine() << "\nblas: " << describe_blas() << "\n";
  std::cout << std::left << std::setw(15) << "row" << std::right << std::setw(10) << "median ms" << std::setw(12)
            << "min ms" << std::setw(12) << "peak MB" << std::setw(12) << "per s" << std::setw(10) << "GFLOP/s"
            << std::setw(8) << "peak %"
            << "  what\n";
  std::map<std::string, double> peak_gflops;  // by precision: the fastest of this run's peak rows
  nlohmann::json out = {{"tool", "flatnet"},    {"threads", threads},      {"repeats", opt.repeats},
                        {"cpu", cpu.summary()}, {"blas", describe_blas()}, {"rows", nlohmann::json::array()}};
  std::vector<std::pair<std::string, bool>> plan;
  for (const auto& name : rows) {
    if (!bench_row_has_precision(name))
      plan.emplace_back(name, false);
    else
      for (bool bf16 : precisions) plan.emplace_back(name, bf16);
  }
  for (const auto& [name, bf16] : plan) {
    opt.bf16 = bf16;
    const auto row = run_bench_row(name, opt);
    const bool is_peak = row.name.rfind("peak_", 0) == 0;
    if (is_peak) peak_gflops[row.peak_kind] = std::max(peak_gflops[row.peak_kind], row.gflops());
    const double gflops = row.gflops();
    const auto peak = peak_gflops.find(row.peak_kind);
    const double share = peak != peak_gflops.end() && !is_peak ? gflops / peak->second : std::nan("");
    print_row(row, gflops, share);
    out["rows"].push_back(row_json(row, gflops, share));
    if (!opt.profile) continue;
    print_profile(row, profile_top);
    auto& ops = out["rows"].back()["profile"] = nlohmann::json::array();
    for (const auto& op : row.ops)
      ops.push_back({{"op", op.name}, {"calls", op.calls}, {"self_ms", op.self_ms}, {"total_ms", op.total_ms}});
  }
  if (r.count("json")) write_text_atomically(settings.json, out.dump(2) + "\n");
  return 0;
}

}  // namespace flatnet::cli
