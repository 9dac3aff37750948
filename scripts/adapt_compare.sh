#!/usr/bin/env bash
# Adapting the shipped model to cameras it never saw (issue 27, part 1), measured:
#   cameras   learned: the separable codes of models/masks/separable; random: seeded random +-1 codes
#             (`flatnet mask camera`, light level kept as the shipped models expect)
#   eval      the 250 held-out display captures of each camera (`flatnet simulate --seed 1 --only val`)
#   methods   Tikhonov; the shipped transpose model as it is; adapted for M minutes
#             (`--init-from models/flatnet-sim-transpose.flatnet --reinit inversion`: the inversion
#             from the new camera's calibration); transfer (the same, with model.inversion.init
#             transfer: the inversion that reproduces the shipped one's W^T P through the new
#             camera); from scratch for M minutes (the same recipe). Runs go in pairs ($PAIRS) that
#             share the 2 cores, one thread each, so the runs of a pair get equal compute.
# Usage: scripts/adapt_compare.sh [RUNS_DIR] [PHOTOS_DIR]   (MINUTES="20 10 40" by default)
# Resumable: what exists is reused (a killed run is resumed; its budget counts the time it had).
# Writes RUNS_DIR/adapt_table.md.
set -euo pipefail
cd "$(dirname "$0")/.."
runs=${1:-$HOME/flatnet-runs/adapt}
photos=${2:-../shared/data/images/train}
minutes=${MINUTES-20 10 40}  # MINUTES="" skips training (table only)
flatnet=${FLATNET:-$PWD/build/flatnet}
shipped=${SHIPPED:-$PWD/models/flatnet-sim-transpose.flatnet}  # SHIPPED: another starting model
mkdir -p "$runs"

camera() {  # NAME -> the camera folder, made once
  local dir=$runs/cam-$1
  if [ ! -f "$dir/camera.yaml" ]; then
    case $1 in
      learned) "$flatnet" mask camera --codes models/masks/separable/codes.mat --centring level --out "$dir" ;;
      random) "$flatnet" mask camera --random-codes 7 --centring level --out "$dir" ;;
    esac
  fi
}

train_run() {  # CAMERA MODE MINUTES (MODE: adapted, transfer or scratch)
  local cam=$1 mode=$2 m=$3 out=$runs/$1-$2-$3min
  local args=(--config configs/sim_transpose.yaml --set "data.camera=$runs/cam-$cam/camera.yaml"
              --set "data.images=$PWD/$photos" --set train.iterations=1000000 --set "train.minutes=$m"
              --threads 1 --out "$out")
  if [ -f "$out/latest.ckpt" ]; then
    "$flatnet" train --out "$out" --resume --set "train.minutes=$m" --threads 1 > "$out.log" 2>&1
  elif [ "$mode" = adapted ]; then
    "$flatnet" train "${args[@]}" --init-from "$shipped" --reinit inversion > "$out.log" 2>&1
  elif [ "$mode" = transfer ]; then
    "$flatnet" train "${args[@]}" --init-from "$shipped" --reinit inversion --set model.inversion.init=transfer \
      --source-camera configs/cameras/sim_level.yaml > "$out.log" 2>&1
  else
    "$flatnet" train "${args[@]}" > "$out.log" 2>&1
  fi
}

reconstruct() {  # CAMERA NAME MODEL
  local eval=$runs/eval-$1
  [ -d "$eval/rec/$2" ] && return 0
  "$flatnet" infer --model "$3" --camera "$runs/cam-$1/camera.yaml" --input "$eval/heldout/val_meas.txt" \
    --out "$eval/rec/$2" > /dev/null
}

for cam in learned random; do
  camera "$cam"
  eval=$runs/eval-$cam
  [ -f "$eval/heldout/val_meas.txt" ] ||
    "$flatnet" simulate --camera "$runs/cam-$cam/camera.yaml" --images "$photos" --out "$eval/heldout" --seed 1 --only val
  [ -d "$eval/rec/tikhonov" ] ||
    "$flatnet" recon --camera "$runs/cam-$cam/camera.yaml" --input "$eval/heldout/val_meas.txt" --out "$eval/rec/tikhonov"
  reconstruct "$cam" shipped "$shipped"
done

# Each pair of runs shares the 2 cores (one thread each): CAMERA:MODE+CAMERA:MODE.
pairs=${PAIRS:-learned:adapted+learned:scratch random:adapted+random:scratch learned:transfer+random:transfer}
for m in $minutes; do
  for pair in $pairs; do
    echo "[$(date +%H:%M)] ${pair/+/ and }, $m minutes each (in parallel, one thread each)"
    pids=()
    for run in ${pair/+/ }; do
      train_run "${run%%:*}" "${run##*:}" "$m" &
      pids+=($!)
    done
    wait "${pids[@]}"
    for run in ${pair/+/ }; do
      cam=${run%%:*} mode=${run##*:}
      reconstruct "$cam" "$mode-${m}min" "$runs/$cam-$mode-${m}min/model.flatnet"
    done
  done
done

{
  echo "| camera | method | PSNR dB | SSIM | NIQE | training steps |"
  echo "|---|---|---|---|---|---|"
  for cam in learned random; do
    "$flatnet" eval --gt "$runs/eval-$cam/heldout/gt" --out "$runs/eval-$cam/rec" > "$runs/eval-$cam/eval.txt" 2>&1
    # metrics.csv: image,method,psnr,ssim,mean_output,mean_truth,niqe; the "mean" rows are the averages.
    grep '^mean,' "$runs/eval-$cam/rec/metrics.csv" | grep -v ',ground truth,' | sort -t, -k2,2 |
      while IFS=, read -r _ method psnr ssim _ _ niqe _rest; do
      steps=""
      [ -f "$runs/$cam-$method/val.csv" ] && steps=$(tail -n 1 "$runs/$cam-$method/val.csv" | cut -d, -f1)
      printf '| %s | %s | %.2f | %.3f | %.2f | %s |\n' "$cam" "$method" "$psnr" "$ssim" "$niqe" "$steps"
    done
  done
} > "$runs/adapt_table.md"
cat "$runs/adapt_table.md"
