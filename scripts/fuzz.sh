#!/usr/bin/env bash
# Coverage-guided fuzzing of every reader of outside bytes (tests/fuzz/fuzz_*.cpp): libFuzzer with
# clang, under AddressSanitizer and UndefinedBehaviorSanitizer, in a build folder of its own
# (build-fuzz/). Too slow for CI; run it before a change to a reader lands.
#   scripts/fuzz.sh [SECONDS] [HARNESS...]   each harness for SECONDS (default 600), all by default
#   FUZZ_JOBS=N                              harnesses at a time (default: the cores)
# Seeds: tests/fuzz/corpus/HARNESS/ (small files flatnet and PyTorch wrote; tests/fuzz/make_seeds.sh).
# The growing corpus stays in build-fuzz/corpus/HARNESS; a crash's input in build-fuzz/findings/.
# Prints per harness: executions per second, coverage (edges, features), and any finding with the
# input that caused it. Exit 1 when any harness found something.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${1:-600}
shift || true
dir=build-fuzz
for p in clang libclang-rt-14-dev; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" && continue
  echo "fuzz: installing $p (clang's libFuzzer)"
  ${SUDO:-$( [ "$(id -u)" -ne 0 ] && echo sudo )} apt-get install -y -qq "$p" > /dev/null
done
if [ ! -f "$dir/build.ninja" ]; then
  CXX=clang++ cmake -S . -B "$dir" -G Ninja -DCMAKE_BUILD_TYPE=None -DFLATNET_FUZZ=ON \
    -DFLATNET_SANITIZE=address,undefined -DFLATNET_BUILD_TESTS=OFF -DFLATNET_WITH_ARAVIS=OFF \
    -DCMAKE_CXX_FLAGS="-O1 -g1" > "$dir.log" 2>&1 || { cat "$dir.log"; exit 1; }
fi
if [ $# -gt 0 ]; then harnesses=("$@"); else
  mapfile -t harnesses < <(ls tests/fuzz/fuzz_*.cpp | xargs -n1 basename | sed 's/\.cpp$//')
fi
echo "fuzz: building ${harnesses[*]} in $dir (log: $dir.log)"
ninja -C "$dir" "${harnesses[@]}" >> "$dir.log" 2>&1 || { tail -n 40 "$dir.log"; exit 1; }

# symbolize=0: a stack dump at an out-of-memory stop runs before libFuzzer writes the input, and
# symbolizing inside a 2 GB process took minutes (the input was lost). Reproduce a finding
# symbolized with: build-fuzz/HARNESS INPUT.
export ASAN_OPTIONS="detect_leaks=0:abort_on_error=1:detect_odr_violation=0:allocator_may_return_null=1:symbolize=0"
export UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1:suppressions=$PWD/tests/sanitizers/ubsan.supp"
export FLATNET_THREADS=1 OMP_NUM_THREADS=1
mkdir -p "$dir/findings" "$dir/logs"
run_one() {  # HARNESS
  local h=$1 corpus=$dir/corpus/$1
  mkdir -p "$corpus"
  [ -d "tests/fuzz/corpus/$h" ] && cp -n tests/fuzz/corpus/"$h"/* "$corpus"/ 2>/dev/null || true
  # 2 GB of memory, 1 GB in one allocation, 30 s per input: a reader that trusts a size it read
  # crosses one of them, and libFuzzer reports it as a finding.
  # The outer timeout: a harness that hangs in its own crash handling cannot hold the summary back.
  (cd "$dir" && timeout -s KILL $((seconds + 300)) ./"$h" -max_total_time="$seconds" -rss_limit_mb=2048 -malloc_limit_mb=1024 -timeout=30 \
    -print_final_stats=1 -artifact_prefix="findings/$h-" "corpus/$h") > "$dir/logs/$h.log" 2>&1 || true
}
jobs=${FUZZ_JOBS:-$(nproc)}
for h in "${harnesses[@]}"; do
  while [ "$(jobs -rp | wc -l)" -ge "$jobs" ]; do sleep 1; done
  echo "fuzz: $h for $seconds s"
  run_one "$h" &
done
wait

status=0
printf '%-22s %10s %12s %10s %s\n' harness execs/s executions coverage finding
for h in "${harnesses[@]}"; do
  log=$dir/logs/$h.log
  # -a: a log holds the inputs' bytes; || true: a harness with no such line shows '?', not the end of the summary.
  execs=$(grep -ao 'stat::number_of_executed_units: [0-9]*' "$log" | awk '{print $2}' | tail -1 || true)
  rate=$(grep -ao 'stat::average_exec_per_sec: *[0-9]*' "$log" | awk '{print $2}' | tail -1 || true)
  cov=$(grep -ao 'cov: [0-9]* ft: [0-9]*' "$log" | tail -1 | awk '{print $2 "/" $4}' || true)
  finding=$(grep -ao "Test unit written to [^ ]*" "$log" | tail -1 | sed 's/Test unit written to //' || true)
  what=$(grep -a -m1 -E "ERROR: (AddressSanitizer|libFuzzer)|runtime error:|fuzz finding:" "$log" | cut -c1-160 || true)
  if [ -n "$finding" ]; then status=1; fi
  printf '%-22s %10s %12s %10s %s\n' "$h" "${rate:-?}" "${execs:-?}" "${cov:-?}" \
    "${finding:+$what (input: $dir/$finding; log: $log)}"
done
exit $status
