#!/usr/bin/env bash
# The main job on a fresh machine: install packages, build, run the end-to-end demo
# (simulated captures of sample photographs -> Tikhonov, TV and the shipped FlatNet models -> metrics).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/build.sh
./build/flatnet demo --out "${1:-demo_out}"
