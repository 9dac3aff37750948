#!/usr/bin/env bash
# Equal-wall-clock ablation of the FlatNet quality recipe (README "The quality recipe, measured at equal wall-clock time"): each variant
# trains for MINUTES of wall time (then Ctrl-C: flatnet saves and exports), two variants at a time
# with one thread each, and is scored on the held-out display captures (data/eval/heldout, made by
# scripts/make_eval_sets.sh). The learning rate is held constant (plus EMA) so that runs of
# different speeds compare fairly; the `cosine` variant sets its iterations from the recipe's speed.
# Usage: scripts/quality_ablation.sh [MINUTES] [OUT] [VARIANT ...]   (defaults: 8, ~/flatnet-runs/ablation, all)
# Prints one line per variant: name, steps, PSNR, SSIM; and writes OUT/ablation.csv.
set -euo pipefail
cd "$(dirname "$0")/.."
minutes=${1:-8}
out=${2:-$HOME/flatnet-runs/ablation}
shift $(( $# > 2 ? 2 : $# )) || true
bin=${FLATNET:-build/flatnet}
heldout=${HELDOUT:-data/eval/heldout}
[ -d "$heldout" ] || { echo "quality_ablation: $heldout missing (run scripts/make_eval_sets.sh)" >&2; exit 2; }
constant="--set train.schedule=halving --set train.lr_halve_every=1000000000 --set train.iterations=100000"
declare -A variants=(
  [recipe]="$constant"
  [no-crop]="$constant --set train.crop=0 --set train.batch=4"
  [fp32]="$constant --set train.precision=fp32"
  [pinv]="$constant --set model.inversion.init=pinv"
  [mse-only]="$constant --set loss.ssim=0"
  [ssim0.2]="$constant --set loss.ssim=0.2"
  [no-ema]="$constant --set train.ema_decay=0"
  [width16]="$constant --set model.unet.width=16"
  [width64]="$constant --set model.unet.width=64"
  [no-light]="$constant --set data.light.exposure_probability=0 --set data.light.lamp_probability=0"
  [cosine]="--set train.schedule=cosine --set train.iterations=${COSINE_STEPS:-300}"
)
order=(recipe no-crop fp32 pinv mse-only no-ema width16 width64 ssim0.2 cosine no-light)
[ $# -gt 0 ] && order=("$@")
mkdir -p "$out"
run_variant() {  # name
  local name=$1 dir=$out/$1
  rm -rf "$dir"
  # shellcheck disable=SC2086
  timeout -s INT "$((minutes * 60))" "$bin" train --config configs/sim_transpose.yaml ${variants[$name]} \
    --set train.val_every=1000000 --set train.val_count=16 --threads 1 --out "$dir" > "$dir.log" 2>&1 || true
  "$bin" infer --model "$dir/model.flatnet" --input "$heldout/val_meas.txt" --out "$dir/eval/$name" --threads 1 >> "$dir.log" 2>&1
  "$bin" eval --gt "$heldout/gt" --out "$dir/eval/$name" --threads 1 > "$dir/eval.txt" 2>&1
}
for ((i = 0; i < ${#order[@]}; i += 2)); do
  run_variant "${order[$i]}" &
  [ $((i + 1)) -lt ${#order[@]} ] && run_variant "${order[$((i + 1))]}" &
  wait
done
echo "variant,steps,psnr,ssim" > "$out/ablation.csv"
for name in "${order[@]}"; do
  steps=$(tail -n 1 "$out/$name/log.csv" | cut -d, -f1)
  scores=$(grep "^mean,$name," "$out/$name/eval/$name/metrics.csv" | cut -d, -f3,4)
  echo "$name,$steps,$scores" | tee -a "$out/ablation.csv"
done
