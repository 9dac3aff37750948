#!/usr/bin/env bash
# Builds flatnet and its tests with sanitizers into a build folder of their own and runs tests
# under them (CI runs the first form).
#   scripts/sanitize.sh            AddressSanitizer + UndefinedBehaviorSanitizer (build-asan/),
#                                  the unit tests (CTest label "unit")
#   scripts/sanitize.sh thread     ThreadSanitizer (build-tsan/), the tests that use threads:
#                                  prefetch loader, parallel loops, Gloo ranks
# Any report fails the run (halt_on_error). LibTorch, OpenMP and oneDNN are not instrumented:
# leak checking is off (LibTorch keeps its registries to exit) and tests/sanitizers/tsan.supp
# names the uninstrumented runtime that ThreadSanitizer cannot see into.
set -euo pipefail
cd "$(dirname "$0")/.."
kind=${1:-address}
case "$kind" in
  address) sanitize=address,undefined dir=build-asan ;;
  thread) sanitize=thread dir=build-tsan ;;
  *) echo "sanitize.sh: address or thread, got '$kind'" >&2; exit 2 ;;
esac
mem_jobs=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 2500000 ))
jobs=${FLATNET_JOBS:-$(( $(nproc) < mem_jobs ? $(nproc) : (mem_jobs > 0 ? mem_jobs : 1) ))}
# -O1 (quicker to build than -O3, still fast to run; line tables for the reports) with the standard
# library's assertions on.
cmake -S . -B "$dir" -G Ninja -DCMAKE_BUILD_TYPE=None -DFLATNET_SANITIZE="$sanitize" \
  -DCMAKE_CXX_FLAGS="-O1 -g1 -D_GLIBCXX_ASSERTIONS" > "$dir.log" 2>&1 || { cat "$dir.log"; exit 1; }
ninja -C "$dir" -j "$jobs" >> "$dir.log" 2>&1 || { tail -n 60 "$dir.log"; exit 1; }
echo "sanitize: built $dir ($sanitize; log in $dir.log)"
supp=$PWD/tests/sanitizers
export ASAN_OPTIONS="detect_leaks=0:halt_on_error=1:abort_on_error=1:detect_odr_violation=0"
export UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1:suppressions=$supp/ubsan.supp"
export TSAN_OPTIONS="halt_on_error=1:second_deadlock_stack=1:suppressions=$supp/tsan.supp"
export FLATNET_TEST_THREADS=1
cd "$dir"
if [ "$kind" = address ]; then
  ctest --output-on-failure -j 2 -L unit
else
  # Threads of our own: simulate's worker pool, parallel_for_index (NIQE), the prefetch loader in
  # training, two Gloo ranks in one process and two ranks as processes.
  ctest --output-on-failure -j 2 -R 'simulate, recon and eval end to end|NIQE rises|batch loader|training resumes bit for bit|distributed: two ranks|distributed: with batch norm|distributed training from the command line'
fi
