#!/usr/bin/env bash
# Configures and builds flatnet (Release, Ninja) into ./build. Used by run.sh and test.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=Release "$@" > build.log 2>&1 || { cat build.log; exit 1; }
# 2 cores: two compile jobs; torch TUs need ~1.5 GB each.
ninja -C build -j "$(nproc)" >> build.log 2>&1 || { tail -n 60 build.log; exit 1; }
echo "build: ok (log in build.log)"
