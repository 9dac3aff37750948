#!/usr/bin/env bash
# flatnet (C++) against the same models in Python PyTorch, on this machine, interleaved:
# for each row, ROUNDS alternations of one `flatnet bench` process and one bench_reference.py
# process (each: warm-up, then REPEATS timed runs), so drifting machine load hits both alike.
# The infer_*/train_* rows run in both precisions on the C++ side (ROW and ROW_bf16) and twice on
# the Python side: its fp32 default and its best easy path (bf16 autocast + channels-last, ROW_best).
# Prints a table and, last, one line per row:
#   ratio <row> <C++ fp32 median / Python fp32 median>
#   ratio_best <row> <C++ best median (fp32 or bf16) / Python best median (its fp32 or bf16 autocast)>   (infer_*/train_* rows)
#   scripts/bench_compare.sh [ROWS] [REPEATS] [ROUNDS]     (defaults: all six rows, 3, 2)
# Environment: THREADS (default: all cores), LEVERS (flatnet's inference levers, default
# fold,channels-last,gemm-up,onednn), PYTHON (default /usr/bin/python3), FLATNET_BIN (default
# build/flatnet), PRECISION (flatnet's, default both), SWEEP=1 also times each
# inference lever alone (C++ only), PY_BEST=0 skips Python's autocast path (on CPUs where bf16 is only
# emulated it is tens of times slower than its fp32, and fp32 is both sides' best).
set -euo pipefail
cd "$(dirname "$0")/.."
rows=${1:-tikhonov,infer_paper,infer_cpu,train_paper,train_cpu,mask_step}
repeats=${2:-3}
rounds=${3:-2}
threads=${THREADS:-$(nproc)}
levers=${LEVERS:-fold,channels-last,gemm-up,onednn}
precision=${PRECISION:-both}
py=${PYTHON:-/usr/bin/python3}  # another interpreter with torch: PYTHON=...
bin=${FLATNET_BIN:-build/flatnet}
[ -x "$bin" ] || bash scripts/build.sh
"$py" -c 'import torch' 2>/dev/null || { echo "bench_compare: $py has no torch (apt install python3-torch)" >&2; exit 2; }
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

bf16_flags=$(grep -m1 '^flags' /proc/cpuinfo | tr ' ' '\n' | grep -E '^(avx512f|avx512_bf16|amx_bf16)$' | tr '\n' ' ' || true)
isa_cap=${ONEDNN_MAX_CPU_ISA:-${DNNL_MAX_CPU_ISA:-}}
echo "machine: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //'), $(nproc) cores, $threads threads, flags: ${bf16_flags:-none of avx512f avx512_bf16 amx_bf16}${isa_cap:+ (oneDNN capped at $isa_cap, both sides)}, $(date -u +%Y-%m-%d)"
# Python runs on the OpenBLAS kernels flatnet runs on (core/blas.hpp: flatnet asks for SkylakeX where
# OpenBLAS 0.3.21 falls back to slower ones), so that both sides' fp32 GEMMs are the same code.
blas_core=$("$bin" bench --rows peak_gemm_fp32 --repeats 1 --warmup 0 --threads 1 | sed -n 's/^blas: OpenBLAS \([A-Za-z0-9]*\).*/\1/p')
if [ -n "$blas_core" ]; then export OPENBLAS_CORETYPE=$blas_core; fi
echo "blas: ${blas_core:+OpenBLAS $blas_core, both sides}"
echo "flatnet levers: $levers; $repeats timed runs after 1 warm-up, $rounds interleaved rounds per row"
IFS=, read -ra row_list <<< "$rows"
for row in "${row_list[@]}"; do
  for ((k = 0; k < rounds; k++)); do
    "$bin" bench --rows "$row" --repeats "$repeats" --threads "$threads" --levers "$levers" --precision "$precision" \
      --json "$tmp/cpp_${row}_$k.json" > /dev/null
    "$py" scripts/bench_reference.py --rows "$row" --repeats "$repeats" --threads "$threads" --json "$tmp/py_${row}_$k.json" > /dev/null
    case "${PY_BEST:-1}$row" in 1infer_*|1train_*)
      "$py" scripts/bench_reference.py --rows "$row" --repeats "$repeats" --threads "$threads" --best \
        --json "$tmp/pybest_${row}_$k.json" > /dev/null ;;
    esac
  done
done
if [ "${SWEEP:-0}" = "1" ]; then  # each lever set, interleaved over the rounds as well
  for ((k = 0; k < rounds; k++)); do
    for l in none fold channels-last,gemm-up fold,channels-last fold,channels-last,gemm-up fold,channels-last,gemm-up,bf16 fold,channels-last,gemm-up,bf16,onednn; do
      "$bin" bench --rows infer_paper --repeats "$repeats" --threads "$threads" --levers "$l" --json "$tmp/lever_${l}_$k.json" > /dev/null
    done
  done
fi

"$py" - "$tmp" "$rows" "$rounds" "${SWEEP:-0}" <<'PY'
import json, statistics, sys, glob, os
tmp, rows, rounds, sweep = sys.argv[1], sys.argv[2].split(","), int(sys.argv[3]), sys.argv[4] == "1"
def load(prefix, row, name=None):
    """Rows called `name` (default: `row`) from each round's JSON of `prefix` for `row`; [] if absent."""
    out = []
    for k in range(rounds):
        path = os.path.join(tmp, "%s_%s_%d.json" % (prefix, row, k))
        if not os.path.exists(path):
            return []
        with open(path) as f:
            out += [r for r in json.load(f)["rows"] if r["name"] == (name or row)]
    return out
def med(rs):
    return statistics.median(r["median_ms"] for r in rs)
print("%-22s %12s %12s %8s %10s %10s %8s" % ("row", "C++ ms", "Python ms", "ratio", "C++ MB", "Python MB", "memory"))
ratios, best_ratios = [], []
for row in rows:
    pairs = [(row, load("cpp", row), load("py", row))]
    if row.split("_")[0] in ("infer", "train"):
        pairs.append((row + "_bf16/_best", load("cpp", row, row + "_bf16"), load("pybest", row, row + "_best")))
    for label, c, p in pairs:
        if not c or not p:
            continue
        cm, pm = med(c), med(p)
        cmem, pmem = max(r["peak_rss_mb"] for r in c), max(r["peak_rss_mb"] for r in p)
        print("%-22s %12.2f %12.2f %8.3f %10.0f %10.0f %+7.1f%%" % (label, cm, pm, cm / pm, cmem, pmem, 100 * (cmem / pmem - 1)))
    c, p = pairs[0][1], pairs[0][2]
    ratios.append((row, med(c) / med(p)))
    if len(pairs) > 1 and pairs[1][2]:
        # Each side's best is its fastest path measured: where bf16 is only emulated (AVX2 CPUs),
        # Python's bf16 autocast is far slower than its own fp32, and fp32 is its best.
        cpp_best = min(med(c), med(pairs[1][1])) if pairs[1][1] else med(c)
        py_best = min(med(p), med(pairs[1][2]))
        best_ratios.append((row, cpp_best / py_best))
if sweep:
    print("\ninference levers, infer_paper (C++ alone):")
    base = None
    for f in ["none", "fold", "channels-last,gemm-up", "fold,channels-last", "fold,channels-last,gemm-up",
              "fold,channels-last,gemm-up,bf16", "fold,channels-last,gemm-up,bf16,onednn"]:
        ms = statistics.median(json.load(open(os.path.join(tmp, "lever_%s_%d.json" % (f, k))))["rows"][0]["median_ms"]
                               for k in range(rounds))
        base = base or ms
        print("  %-34s %10.1f ms  %5.2fx" % (f, ms, base / ms))
for row, r in ratios:
    print("ratio %s %.3f" % (row, r))
for row, r in best_ratios:
    print("ratio_best %s %.3f" % (row, r))
PY
