#!/usr/bin/env bash
# Starts N local ranks of `flatnet train` (data-parallel, c10d/Gloo over 127.0.0.1), the way
# torchrun would: WORLD_SIZE, RANK, MASTER_ADDR, MASTER_PORT in each rank's environment.
#   scripts/launch_local.sh N CONFIG --out RUN [more flatnet train flags, e.g. --set train.iterations=50]
# With --resume the run continues with its own config (RUN/config.yaml): CONFIG is not passed on.
# The cores are split between the ranks (--threads). If one rank fails, the others are stopped.
# Rank 0 writes RUN/; ranks 1.. log to RUN.rankR.log.
set -euo pipefail
if [ $# -lt 2 ]; then
  echo "usage: $0 N CONFIG --out RUN [flatnet train flags]" >&2
  exit 2
fi
n=$1 config=$2
shift 2
root="$(cd "$(dirname "$0")/.." && pwd)"
bin="${FLATNET_BIN:-$root/build/flatnet}"
[ -x "$bin" ] || { echo "launch_local: $bin not built (scripts/build.sh)" >&2; exit 2; }
out=""
config_flag=(--config "$config")
args=("$@")
for ((i = 0; i < ${#args[@]}; i++)); do
  [ "${args[$i]}" = "--out" ] && out="${args[$((i + 1))]:-}"
  [ "${args[$i]}" = "--resume" ] && config_flag=()
done
[ -n "$out" ] || { echo "launch_local: --out RUN is required" >&2; exit 2; }
threads=$(( $(nproc) / n )); [ "$threads" -ge 1 ] || threads=1
export WORLD_SIZE=$n MASTER_ADDR=127.0.0.1 MASTER_PORT=${MASTER_PORT:-$((29500 + RANDOM % 1000))}
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; }
trap cleanup INT TERM
for ((r = 0; r < n; r++)); do
  if [ "$r" -eq 0 ]; then
    RANK=$r "$bin" train "${config_flag[@]}" --threads "$threads" "$@" &
  else
    mkdir -p "$(dirname "$out")"
    RANK=$r "$bin" train "${config_flag[@]}" --threads "$threads" "$@" > "$out.rank$r.log" 2>&1 &
  fi
  pids+=($!)
done
status=0
for p in "${pids[@]}"; do
  if ! wait "$p"; then
    rc=$?
    [ "$status" -eq 0 ] && status=$rc
    cleanup
  fi
done
exit "$status"
