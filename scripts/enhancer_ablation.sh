#!/usr/bin/env bash
# The thesis's Figure 5.4, redone at equal wall-clock time (issue 26; docs/training.md "Which
# enhancer"): U-Net, DnCNN, RCAN and NAFNet behind FlatNet's trainable inversion (transpose
# initialisation), and the naive model (a fixed Tikhonov reconstruction + U-Net), each trained
# from scratch for MINUTES of wall time on the same simulated data with the shipped regression
# recipe (configs/sim_transpose.yaml: MSE + 0.2 SSIM, cosine schedule spanning the budget, EMA).
# Runs go one at a time on one thread (the other core stays free), so every enhancer gets the same
# compute. RCAN is the authors' block at a CPU's size (3 groups of 4 blocks, width 32: its default
# 5x10x64 needs ~40 GB at batch 8 and ~2 s per 256x256 image). Then every model is scored on the held-out, dim and lamp sets (scripts/eval_tables.sh;
# data/eval from scripts/make_eval_sets.sh) with PSNR, SSIM, NIQE, colour and detail kept.
# Usage: scripts/enhancer_ablation.sh [MINUTES] [OUT] [VARIANT ...]
#   (defaults: 15, ~/flatnet-runs/q26/enhancers, all of: unet dncnn rcan nafnet naive)
# Resumable: a variant whose run has model.flatnet and no newer checkpoint is kept; an interrupted
# one resumes within its budget. Writes OUT/enhancers.csv (variant,steps,set,psnr,ssim,niqe,colour,detail).
set -euo pipefail
cd "$(dirname "$0")/.."
minutes=${1:-15}
out=${2:-$HOME/flatnet-runs/q26/enhancers}
shift $(( $# > 2 ? 2 : $# )) || true
bin=${FLATNET:-$PWD/build/flatnet}
declare -A variants=(
  [unet]="--config configs/sim_transpose.yaml"
  [dncnn]="--config configs/sim_transpose.yaml --set model.enhancer=dncnn"
  [rcan]="--config configs/sim_transpose.yaml --set model.enhancer=rcan --set model.rcan.groups=3 --set model.rcan.blocks=4 --set model.rcan.width=32"
  [nafnet]="--config configs/sim_transpose.yaml --set model.enhancer=nafnet"
  [naive]="--config configs/sim_naive.yaml"
)
order=(unet dncnn rcan nafnet naive)
[ $# -gt 0 ] && order=("$@")
mkdir -p "$out"
for name in "${order[@]}"; do
  [ -n "${variants[$name]+x}" ] || { echo "enhancer_ablation: unknown variant $name" >&2; exit 2; }
  dir=$out/$name
  if [ -f "$dir/done" ]; then continue; fi
  echo "[$(date +%H:%M)] $name: $minutes minutes, one thread"
  if [ -f "$dir/latest.ckpt" ]; then
    "$bin" train --out "$dir" --resume --set "train.minutes=$minutes" --threads 1 >> "$dir.log" 2>&1 ||
      { echo "enhancer_ablation: $name failed (see $dir.log)" >&2; continue; }
  else
    # shellcheck disable=SC2086
    "$bin" train ${variants[$name]} --set train.iterations=1000000 --set "train.minutes=$minutes" \
      --threads 1 --out "$dir" > "$dir.log" 2>&1 || { echo "enhancer_ablation: $name failed (see $dir.log)" >&2; continue; }
  fi
  touch "$dir/done"
done
models=() done_order=()
for name in "${order[@]}"; do
  [ -f "$out/$name/done" ] && models+=("$name=$out/$name/model.flatnet") && done_order+=("$name")
done
order=("${done_order[@]}")
TV_COUNT=-1 FLATNET=$bin scripts/eval_tables.sh "$out/eval" "${models[@]}"
echo "variant,steps,set,psnr,ssim,niqe,colour,detail" > "$out/enhancers.csv"
for name in "${order[@]}"; do
  steps=$(tail -n 1 "$out/$name/log.csv" | cut -d, -f1)
  for set in heldout dim lamp; do
    row=$(grep "^mean,$name," "$out/eval/$set/metrics.csv" | cut -d, -f3,4,7,8,9 || true)
    echo "$name,$steps,$set,$row" >> "$out/enhancers.csv"
  done
done
cat "$out/enhancers.csv"
