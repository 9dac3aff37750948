#!/usr/bin/env bash
# The camera fit (docs/own-camera.md#does-a-capture-fit-the-model), validated on many captures:
#   reference  the reference camera's display captures, dim (0.33 of the light) and lamp-lit sets:
#              every capture should fit (no false alarm)
#   other      captures of two other cameras, through the reference camera's calibration: learned
#              separable codes (models/masks/separable) and random +-1 codes; every one should not
#   prototype  FlatNet's real prototype captures (../shared/data/flatnet/fc_*.png)
# Each set is reconstructed with Tikhonov through the reference camera (configs/cameras/sim_level.yaml,
# the camera the shipped models were trained with): recon writes camera_fit.csv, as infer does.
# Usage: scripts/camera_fit_check.sh [RUNS_DIR] [PHOTOS_DIR] [COUNT]   (COUNT images per set, default 250)
#   JUDGE=CAMERA.yaml: judge with that camera instead (e.g. one `flatnet calibrate --dataset` identified,
#   noise model included); its results go to RUNS_DIR/judge-NAME/.
# Writes RUNS_DIR/camera_fit.md (RUNS_DIR/judge-NAME/camera_fit.md with JUDGE).
set -euo pipefail
cd "$(dirname "$0")/.."
runs=${1:-$HOME/flatnet-runs/camera-fit}
photos=${2:-../shared/data/images/train}
count=${3:-250}
flatnet=${FLATNET:-$PWD/build/flatnet}
reference=configs/cameras/sim_level.yaml
judge=${JUDGE:-$reference}
fits=$runs
[ -z "${JUDGE:-}" ] || fits=$runs/judge-$(basename "$(dirname "$JUDGE")")
mkdir -p "$runs" "$fits"

make_camera() {  # NAME ARGS...: a camera folder from `flatnet mask camera`, made once
  local dir=$runs/cam-$1
  shift
  [ -f "$dir/camera.yaml" ] || "$flatnet" mask camera "$@" --centring level --out "$dir" > /dev/null
}
make_camera learned --codes models/masks/separable/codes.mat
make_camera random --random-codes 7

simulate() {  # SET CAMERA ARGS...
  local set=$1 camera=$2
  shift 2
  [ -f "$runs/$set/val_meas.txt" ] ||
    "$flatnet" simulate --images "$photos" --camera "$camera" --out "$runs/$set" --limit "$count" \
      --val-fraction 1 --seed 5 --only val "$@" > /dev/null
}
simulate reference "$reference"
simulate dim "$reference" --exposure 0.33
simulate lamp "$reference" --lamp --lamp-gain 20
simulate learned "$runs/cam-learned/camera.yaml"
simulate random "$runs/cam-random/camera.yaml"

fit_of() {  # SET INPUT: Tikhonov through the judging camera; the fit lands in camera_fit.csv
  local out=$fits/fit-$1
  [ -f "$out/camera_fit.csv" ] ||
    "$flatnet" recon --method tikhonov --camera "$judge" --input "$2" --out "$out" --force > /dev/null 2>&1 || true
  # camera_fit.csv: name,fit,leak,alone,matches (alone: the capture's own tests; matches: with its batch's)
  awk -F, 'NR > 1 { n++; a += $4; m += $5; if ($2 == "nan") { s++; next }; j++
                     if (j == 1 || $2 > max) max = $2; if (j == 1 || $2 < min) min = $2
                     if ($3 != "nan") { k++; if (k == 1 || $3 > lmax) lmax = $3; if (k == 1 || $3 < lmin) lmin = $3 } }
           END { printf "| %d | %d | %d | %d | %.4f - %.4f | %.3f - %.3f |", n, a, m, s, min, max, lmin, lmax }' "$out/camera_fit.csv"
}
{
  echo "| set | captures | fit alone | fit, judged with their batch | saturated (not judged alone) | fit, lowest - highest | leak, lowest - highest |"
  echo "|---|---|---|---|---|---|---|"
  for set in reference dim lamp learned random; do
    echo "| $set $(fit_of "$set" "$runs/$set/val_meas.txt")"
  done
  if ls ../shared/data/flatnet/fc_*.png > /dev/null 2>&1; then
    echo "| FlatNet prototype $(fit_of prototype '../shared/data/flatnet/fc_*.png')"
  fi
} | tee "$fits/camera_fit.md"
