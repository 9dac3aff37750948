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
if [ $# -gt 0 ]; then
  ctest --output-on-failure -j 2 -L "$1"
else
  ctest --output-on-failure -j 2
fi
