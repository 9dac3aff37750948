#!/usr/bin/env bash
# The README's FlatNet tables: every method on the held-out display captures and the dim and lamp
# sets (scripts/make_eval_sets.sh), scored by `flatnet eval` (PSNR, SSIM +- over images, brightness).
# Usage: scripts/eval_tables.sh OUT [NAME=MODEL.flatnet ...]
#   (default models: transpose and calibfree from models/). TV is slow (FISTA, ~3.7 s per capture
#   on 2 cores): it runs on the first TV_COUNT captures of each set (default 50; 0: all).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: scripts/eval_tables.sh OUT [NAME=MODEL ...]}
shift
bin=${FLATNET:-build/flatnet}
sets=${SETS:-heldout dim lamp}
tv_count=${TV_COUNT:-50}
models=("$@")
[ ${#models[@]} -gt 0 ] || models=(flatnet-transpose=models/flatnet-sim-transpose.flatnet flatnet-calibfree=models/flatnet-sim-calibfree.flatnet)
for set in $sets; do
  data=data/eval/$set
  [ -f "$data/val_meas.txt" ] || { echo "eval_tables: $data missing (scripts/make_eval_sets.sh)" >&2; exit 2; }
  mkdir -p "$out/$set"
  [ -d "$out/$set/tikhonov" ] || "$bin" recon --method tikhonov --input "$data/val_meas.txt" --out "$out/$set/tikhonov"
  if [ "$tv_count" != "-1" ] && [ ! -d "$out/$set/tv" ]; then
    list=$data/val_meas.txt
    if [ "$tv_count" -gt 0 ]; then list=$out/$set/tv_list.txt; sed 's|^|'"$PWD/$data"'/|' "$data/val_meas.txt" | head -n "$tv_count" > "$list"; fi
    "$bin" recon --method tv --input "$list" --out "$out/$set/tv"
  fi
  for m in "${models[@]}"; do
    name=${m%%=*} file=${m#*=}
    [ -d "$out/$set/$name" ] || "$bin" infer --model "$file" --input "$data/val_meas.txt" --out "$out/$set/$name"
  done
  echo "== $set ($data)"
  "$bin" eval --gt "$data/gt" --out "$out/$set" | tee "$out/$set/table.txt"
done
