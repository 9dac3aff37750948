#!/usr/bin/env bash
# Separable cameras compared through the real pipeline: for each code pair, the camera
# (`flatnet mask camera`, calibration with 3 % error), the 250 held-out display captures
# (`flatnet simulate --seed 1 --only val`, the same photographs and noise seeds for every camera),
# Tikhonov at four regularisers (the camera file's way of choosing one), scored by `flatnet eval`.
# Usage: scripts/separable_compare.sh OUT NAME=CODES.mat [NAME=CODES.mat ...]
#   (default: mls=models/camera/codes_mls.mat)
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: scripts/separable_compare.sh OUT NAME=CODES.mat ...}
shift
bin=${FLATNET:-build/flatnet}
photos=${PHOTOS:-../shared/data/images/train}
pairs=("$@")
[ ${#pairs[@]} -gt 0 ] || pairs=(mls=models/camera/codes_mls.mat)
mkdir -p "$out"
for p in "${pairs[@]}"; do
  name=${p%%=*} codes=${p#*=}
  [ -f "$out/cam_$name/camera.yaml" ] || "$bin" mask camera --codes "$codes" --out "$out/cam_$name"
  "$bin" simulate --camera "$out/cam_$name/camera.yaml" --images "$photos" --out "$out/heldout_$name" --seed 1 --only val
  for lambda in 3e-5 1e-4 3e-4 1e-3; do
    [ -d "$out/rec_$name/tikhonov_$lambda" ] || "$bin" recon --camera "$out/cam_$name/camera.yaml" --lambda "$lambda" \
      --input "$out/heldout_$name/val_meas.txt" --out "$out/rec_$name/tikhonov_$lambda"
  done
  echo "== $name ($codes)"
  "$bin" eval --gt "$out/heldout_$name/gt" --out "$out/rec_$name" --niqe none | tee "$out/table_$name.txt"
done
