#!/usr/bin/env bash
# Each bench error's cost alone (docs/own-camera.md, "A real bench"), on the random-codes camera of
# scripts/own_camera_check.sh: for every error, the held-out photographs of that run and TRAIN of its
# training photographs are captured with that error alone; the held-out captures are reconstructed by
# Tikhonov with the camera's exact main-term calibration and with the one `calibrate --dataset`
# identifies from the TRAIN pairs (TRAIN=0: the exact one only); `flatnet eval` scores them beside the
# ideal bench.
# Usage: scripts/bench_errors_check.sh RUNS_DIR   (TRAIN=100)
# RUNS_DIR is an own_camera_check.sh folder of the ideal bench (its cam/, cam-exact/, photos-*).
# Resumable: what exists is reused. Writes RUNS_DIR/errors/errors.md.
set -euo pipefail
cd "$(dirname "$0")/.."
runs=$1
train=${TRAIN:-100}
flatnet=${FLATNET:-$PWD/build/flatnet}
[ -f "$runs/cam/camera.yaml" ] && [ -d "$runs/photos-heldout" ] || {
  echo "error: $runs: run scripts/own_camera_check.sh $runs first (it makes the camera and the photo folders)" >&2
  exit 1
}
out=$runs/errors
mkdir -p "$out/rec"
errors=(
  "ideal:"
  "crosstalk:crosstalk: 0.2"
  "rotation:mask_rotation: 0.004"
  "second_term:second_term: 0.04"
  "flicker:flicker: 0.03"
  "stray_light:stray_light: 0.01"
  "hot_pixels:hot_pixels: 300"
  "display:display_shift: 1.5, display_scale: 1.01"
)
for entry in "${errors[@]}"; do
  name=${entry%%:*}
  bench=${entry#*:}
  dir=$out/$name
  mkdir -p "$dir"
  camera=$runs/cam/camera-$name.yaml
  { cat "$runs/cam/camera.yaml"; [ -z "$bench" ] || echo "bench: {$bench}"; } > "$camera"
  [ -f "$dir/heldout/val_meas.txt" ] || "$flatnet" simulate --images "$runs/photos-heldout" --camera "$camera" \
    --val-fraction 1 --only val --seed 2 --out "$dir/heldout" > /dev/null 2>&1
  [ -d "$out/rec/$name-exact" ] || "$flatnet" recon --method tikhonov --camera "$runs/cam/camera.yaml" \
    --calib "$runs/cam-exact/calib.mat" --input "$dir/heldout/val_meas.txt" --out "$out/rec/$name-exact" > /dev/null 2>&1
  [ "$train" = 0 ] && continue
  if [ ! -f "$dir/ds/train_meas.txt" ]; then
    rm -rf "$dir/photos-train" && mkdir -p "$dir/photos-train"
    find "$runs/photos-train/" -maxdepth 1 | sort | sed -n "2,$((train + 1))p" | while read -r f; do ln -s "$(readlink -f "$f")" "$dir/photos-train/"; done
    "$flatnet" simulate --images "$dir/photos-train" --camera "$camera" --val-fraction 0.02 --seed 1 \
      --out "$dir/ds" > /dev/null 2>&1
  fi
  [ -f "$dir/cal/calib.mat" ] || { mkdir -p "$dir/cal" && "$flatnet" calibrate --dataset "$dir/ds" \
    --camera "$runs/geometry.yaml" --out "$dir/cal/calib.mat" > "$dir/cal/log.txt" 2>&1; }
  [ -d "$out/rec/$name-dataset" ] || "$flatnet" recon --method tikhonov --camera "$dir/cal/camera.yaml" \
    --input "$dir/heldout/val_meas.txt" --out "$out/rec/$name-dataset" > /dev/null 2>&1
done
"$flatnet" eval --gt "$out/ideal/heldout/gt" --out "$out/rec" > "$out/eval.txt" 2>&1 || true
{
  echo "each error alone: Tikhonov of the held-out captures with the exact main-term calibration and with"
  echo "calibrate --dataset from $train pairs (0: not run)"
  echo
  for entry in "${errors[@]}"; do
    name=${entry%%:*}
    [ -f "$out/$name/cal/log.txt" ] &&
      echo "$name: $(grep -h -E '^(hot pixels|shift structure|sensor noise|colour mix)' "$out/$name/cal/log.txt" | tr '\n' ';')"
  done
  echo
  cat "$out/eval.txt"
} | tee "$out/errors.md"
