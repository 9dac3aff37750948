#!/usr/bin/env bash
# Configures and builds flatnet (Release, Ninja) into ./build. Used by run.sh and test.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=Release "$@" > build.log 2>&1 || { cat build.log; exit 1; }
# One compile job per core (FLATNET_JOBS overrides), at most one per 2 GB of memory: a TU that
# includes torch needs ~1.5 GB.
mem_jobs=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 2000000 ))
jobs=${FLATNET_JOBS:-$(( $(nproc) < mem_jobs ? $(nproc) : (mem_jobs > 0 ? mem_jobs : 1) ))}
ninja -C build -j "$jobs" >> build.log 2>&1 || { tail -n 60 build.log; exit 1; }
echo "build: ok (log in build.log)"
