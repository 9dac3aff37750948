#!/usr/bin/env bash
# Builds and runs the whole test suite (CTest labels: unit, slow). Exits non-zero on failure.
# Pass a CTest label to narrow it: scripts/test.sh unit
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/build.sh
cd build
# Two test processes at a time, one intra-op thread each (tests/test_main.cpp).
export FLATNET_TEST_THREADS=${FLATNET_TEST_THREADS:-1}
# Threads that wait sleep instead of spinning: beside other jobs on the machine a spinning OpenMP
# thread holds a core another process needs (a training step 1.9x slower; passive waiting halves
# that, docs/results/performance.md). libgomp reads it when it loads, so it is set here.
export OMP_WAIT_POLICY=${OMP_WAIT_POLICY:-PASSIVE}
# Every process the tests start (over 250 in the unit label: flatnet commands and test groups) loads
# LibTorch, 24,600 page faults before main; with glibc's malloc asking for transparent huge pages 8,200,
# a start 0.7 s instead of 0.9-1.3 s (docs/design.md). glibc reads it when a process starts, so it is
# set here; a tunable list already set is kept.
[[ ${GLIBC_TUNABLES:-} == *glibc.malloc.hugetlb* ]] ||
  export GLIBC_TUNABLES=${GLIBC_TUNABLES:+$GLIBC_TUNABLES:}glibc.malloc.hugetlb=1
start=$SECONDS
status=0
ctest --output-on-failure -j 2 ${1:+-L "$1"} | tee ctest.log || status=$?
# The time, and the ten slowest tests (CTest's "N/M Test #K: name ... Passed 12.34 sec" lines).
echo "tests: $((SECONDS - start)) s on $(nproc) cores${1:+ (label $1)}; the ten slowest:"
grep -E 'Test +#[0-9]+: .* sec$' ctest.log | sed -E 's/^.*Test +#[0-9]+: (.*[^ .]) *\.+ *[A-Za-z*]+.* +([0-9.]+) sec$/\2 s  \1/' |
  sort -g -r | sed -n '1,10p'  # sed reads all: head would close the pipe early, and pipefail end the script with 141
exit "$status"
