#!/usr/bin/env bash
# A camera that reaches flatnet only as display-capture pairs (docs/own-camera.md), measured:
#   camera     random +-1 codes (`flatnet mask camera --random-codes 7 --centring level`): a FlatCam no
#              shipped model saw; its rig stands in for the world and is used only to simulate
#   pairs      TRAIN display captures of the first photographs; held-out: HELDOUT captures of the last
#   calibrate  `calibrate --dataset` from 100 and TRAIN pairs, against the rig's truth
#   Tikhonov   on the held-out captures with each calibration, beside the ideal one (the rig's exact
#              response), the 3 %-error one a careful Hadamard procedure gives (`mask camera`'s calib.mat)
#              and the simulated Hadamard procedure itself (`calibrate --rig`: 4 x 256 noisy captures)
#   adapt      the shipped transpose model adapted for MINUTES on the TRAIN pairs alone, with the
#              dataset's calibration (skipped when MINUTES=0)
#   bench      BENCH="crosstalk: 0.2, mask_rotation: 0.004, ..." gives the camera a real bench's errors
#              (the camera file's bench: section, docs/camera-file.md); the user's geometry file does not
#              state them. Without BENCH: the ideal bench, with the same codes.
# Usage: scripts/own_camera_check.sh [RUNS_DIR] [PHOTOS_DIR]   (TRAIN=500 HELDOUT=100 MINUTES=20)
# Resumable: what exists is reused. Writes RUNS_DIR/own_camera.md.
set -euo pipefail
cd "$(dirname "$0")/.."
runs=${1:-$HOME/flatnet-runs/own-camera}
photos=$(cd "${2:-../shared/data/images/train}" && pwd)
train=${TRAIN:-500}
heldout=${HELDOUT:-100}
minutes=${MINUTES:-20}
flatnet=${FLATNET:-$PWD/build/flatnet}
mkdir -p "$runs"
cam=$runs/cam
[ -f "$cam/camera.yaml" ] || "$flatnet" mask camera --random-codes 7 --centring level --out "$cam" > /dev/null
if [ -n "${BENCH:-}" ] && ! grep -q '^bench:' "$cam/camera.yaml"; then echo "bench: {$BENCH}" >> "$cam/camera.yaml"; fi
[ -f "$runs/cam-exact/camera.yaml" ] ||
  "$flatnet" mask camera --codes "$cam/codes.mat" --calib-error 0 --centring level --out "$runs/cam-exact" > /dev/null
# What the user knows: the geometry (the rig line stays only so that calibrate can print its error).
grep -v -E '^(calibration|noise_gain|noise_floor|dark|bench):' "$cam/camera.yaml" | sed "s|^rig: .*|rig: $cam/rig.mat|" > "$runs/geometry.yaml"

photo_folder() {  # NAME FIRST COUNT: symlinks to a slice of the sorted photographs
  local dir=$runs/photos-$1
  [ -d "$dir" ] && return 0
  mkdir -p "$dir"
  find "$photos" -maxdepth 1 -type f | sort | sed -n "$2,$(($2 + $3 - 1))p" | while read -r f; do ln -s "$f" "$dir/"; done
}
total=$(find "$photos" -maxdepth 1 -type f | wc -l)
photo_folder train 1 "$train"
photo_folder heldout $((total - heldout + 1)) "$heldout"
[ -f "$runs/ds/train_meas.txt" ] ||
  "$flatnet" simulate --images "$runs/photos-train" --camera "$cam/camera.yaml" --val-fraction 0.02 --seed 1 --out "$runs/ds" > /dev/null
[ -f "$runs/heldout/val_meas.txt" ] ||
  "$flatnet" simulate --images "$runs/photos-heldout" --camera "$cam/camera.yaml" --val-fraction 1 --only val --seed 2 --out "$runs/heldout" > /dev/null

calibrate() {  # PAIRS
  local out=$runs/cal-$1
  [ -f "$out/calib.mat" ] && return 0
  mkdir -p "$out"
  /usr/bin/time -f "%e s, %M KB" "$flatnet" calibrate --dataset "$runs/ds" --camera "$runs/geometry.yaml" --limit "$1" \
    --out "$out/calib.mat" > "$out/log.txt" 2>&1
}
for n in 100 "$train"; do calibrate "$n"; done
[ -f "$runs/cal-hadamard/calib.mat" ] || { mkdir -p "$runs/cal-hadamard" &&
  "$flatnet" calibrate --rig "$cam/camera.yaml" --out "$runs/cal-hadamard/calib.mat" > "$runs/cal-hadamard/log.txt" 2>&1; }

tikhonov() {  # NAME CALIB
  [ -d "$runs/rec/$1" ] || "$flatnet" recon --method tikhonov --camera "$cam/camera.yaml" --calib "$2" \
    --input "$runs/heldout/val_meas.txt" --out "$runs/rec/$1" > /dev/null 2>&1
}
tikhonov exact "$runs/cam-exact/calib.mat"
tikhonov hadamard-3pct "$cam/calib.mat"
tikhonov hadamard-sim "$runs/cal-hadamard/calib.mat"
for n in 100 "$train"; do tikhonov "dataset-$n" "$runs/cal-$n/calib.mat"; done

if [ "$minutes" != 0 ]; then
  run=$runs/adapt-${minutes}min
  if [ ! -f "$run/model.flatnet" ] || ! grep -q "steps" "$run.log" 2>/dev/null; then
    if [ -f "$run/latest.ckpt" ]; then
      "$flatnet" train --out "$run" --resume --set "train.minutes=$minutes" > "$run.log" 2>&1
    else
      "$flatnet" train --config configs/sim_transpose.yaml --init-from models/flatnet-sim-transpose.flatnet \
        --reinit inversion --set data.source=dataset --set "data.dataset=$runs/ds" \
        --set "data.camera=$runs/cal-$train/camera.yaml" --set "train.minutes=$minutes" \
        --out "$run" > "$run.log" 2>&1
    fi
  fi
  [ -d "$runs/rec/adapted-${minutes}min" ] || "$flatnet" infer --model "$run/model.flatnet" \
    --input "$runs/heldout/val_meas.txt" --out "$runs/rec/adapted-${minutes}min" > "$runs/rec-adapted.log" 2>&1
  [ -d "$runs/rec/shipped" ] || "$flatnet" infer --model models/flatnet-sim-transpose.flatnet --camera "$cam/camera.yaml" \
    --input "$runs/heldout/val_meas.txt" --out "$runs/rec/shipped" > "$runs/rec-shipped.log" 2>&1
fi
"$flatnet" eval --gt "$runs/heldout/gt" --out "$runs/rec" > "$runs/eval.txt" 2>&1 || true
{
  echo "calibration errors (forward model, against the rig's truth):"
  for n in 100 "$train"; do echo "  dataset $n pairs: $(grep -h 'relative error' "$runs/cal-$n/log.txt" || true) ($(tail -1 "$runs/cal-$n/log.txt"))"; done
  echo "  simulated Hadamard (1024 captures): $(grep -h 'relative error' "$runs/cal-hadamard/log.txt" || true)"
  echo
  cat "$runs/eval.txt"
} | tee "$runs/own_camera.md"
