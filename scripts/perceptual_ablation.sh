#!/usr/bin/env bash
# The perceptual terms of issue 26, measured one at a time at equal wall-clock time (README
# "Sharper pictures: the perceptual terms, measured"). Every variant fine-tunes the shipped
# transpose model (`--init-from`: the enhancer and inversion kept, a fresh discriminator and
# optimisers) for MINUTES of wall time with the shipped recipe (configs/sim_transpose.yaml) plus
# its terms, at a constant learning rate (plus EMA) so that variants of different step costs
# compare fairly. Two variants run at a time, one thread each, so both get equal compute.
# Each is scored on the 250 held-out display captures (data/eval/heldout, scripts/make_eval_sets.sh):
# PSNR, SSIM, NIQE, colourfulness and detail kept (`flatnet eval`).
# Usage: scripts/perceptual_ablation.sh [MINUTES] [OUT] [VARIANT ...]   (defaults: 15, ~/flatnet-runs/q26/ablation, all)
# Environment: CONFIG (the recipe; default configs/sim_transpose.yaml), SHIPPED (the starting model),
# LR (the constant learning rate, default 1.0e-4), HELDOUT, FLATNET.
# Resumable: a variant with eval.txt is kept; a run stopped early is resumed within its budget.
# Writes OUT/ablation.csv: variant,steps,psnr,ssim,niqe,colour_kept,detail_kept,stripes.
set -euo pipefail
cd "$(dirname "$0")/.."
minutes=${1:-15}
out=${2:-$HOME/flatnet-runs/q26/ablation}
shift $(( $# > 2 ? 2 : $# )) || true
bin=${FLATNET:-$PWD/build/flatnet}
heldout=${HELDOUT:-data/eval/heldout}
shipped=${SHIPPED:-models/flatnet-sim-transpose.flatnet}
config=${CONFIG:-configs/sim_transpose.yaml}
[ -f "$heldout/val_meas.txt" ] || { echo "perceptual_ablation: $heldout missing (run scripts/make_eval_sets.sh)" >&2; exit 2; }
lr=${LR:-1.0e-4}
constant=(--set train.schedule=halving --set train.lr_halve_every=1000000000 --set "train.lr=$lr"
          --set train.iterations=1000000 --set train.val_every=250 --set train.val_count=16)
declare -A variants=(
  [recipe]=""
  [adversarial]="--set loss.adversarial=0.01"
  [feature-matching]="--set loss.adversarial=0.01 --set loss.feature_matching=0.05"
  [frequency]="--set loss.frequency=5"
  [chroma]="--set loss.chroma=0.5"
  [gradient]="--set loss.gradient=0.5"
  # issue 112 (run with CONFIG=configs/gan_transpose.yaml: the GAN recipe plus or minus the term)
  [no-detail]="--set loss.detail=0"
  [detail-1]="--set loss.detail=1"
  [detail-3]="--set loss.detail=3"
  [random-features]="--set loss.detail=0 --set loss.random_features=0.1"
  [detail+random-features]="--set loss.detail=3 --set loss.random_features=0.1"
  [adversarial-0.03]="--set loss.detail=0 --set loss.adversarial=0.03"
  [detail-10]="--set loss.detail=10"
  [detail-30]="--set loss.detail=30"
)
order=(recipe adversarial feature-matching frequency chroma gradient)
[ $# -gt 0 ] && order=("$@")
for name in "${order[@]}"; do
  [ -n "${variants[$name]+set}" ] || variants[$name]=${VARIANT_ARGS:?"unknown variant $name: give its --set flags in VARIANT_ARGS"}
done
mkdir -p "$out"

run_variant() {  # NAME
  local name=$1 dir=$out/$1
  [ -f "$dir/eval.txt" ] && return 0
  if [ -f "$dir/latest.ckpt" ]; then
    "$bin" train --out "$dir" --resume --set "train.minutes=$minutes" --threads 1 >> "$dir.log" 2>&1
  else
    # shellcheck disable=SC2086
    "$bin" train --config "$config" "${constant[@]}" ${variants[$name]} --set "train.minutes=$minutes" \
      --init-from "$shipped" --threads 1 --out "$dir" > "$dir.log" 2>&1
  fi
  "$bin" infer --model "$dir/model.flatnet" --input "$heldout/val_meas.txt" --out "$dir/eval/$name" --threads 1 >> "$dir.log" 2>&1
  "$bin" eval --gt "$heldout/gt" --out "$dir/eval/$name" --threads 1 > "$dir/eval.txt.tmp" 2>&1
  mv "$dir/eval.txt.tmp" "$dir/eval.txt"
}

for ((i = 0; i < ${#order[@]}; i += 2)); do
  echo "[$(date +%H:%M)] ${order[$i]} ${order[$((i + 1))]:-}, $minutes minutes each"
  run_variant "${order[$i]}" &
  pids=($!)
  if [ $((i + 1)) -lt ${#order[@]} ]; then run_variant "${order[$((i + 1))]}" & pids+=($!); fi
  wait "${pids[@]}"
done

# metrics.csv mean row: mean,method,psnr,ssim,mean_output,mean_truth,niqe,colour_kept,detail_kept,stripes
echo "variant,steps,psnr,ssim,niqe,colour_kept,detail_kept,stripes" > "$out/ablation.csv"
for name in "${order[@]}"; do
  steps=$(tail -n 1 "$out/$name/log.csv" | cut -d, -f1)
  scores=$(grep "^mean,$name," "$out/$name/eval/$name/metrics.csv" | cut -d, -f3,4,7,8,9,10)
  echo "$name,$steps,$scores" | tee -a "$out/ablation.csv"
done
