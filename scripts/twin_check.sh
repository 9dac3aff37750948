#!/usr/bin/env bash
# A twin of FlatNet's prototype (issue 90 #5): a camera a user knows only by four captures and
# someone's Tikhonov pictures of them, whose captures hold light the separable model misses. The whole
# path is scored on held-out photographs through it, against the same path with the twin's truth.
#   camera     random +-1 codes (`flatnet mask camera --random-codes 11 --centring level`) with a real
#              bench's errors the separable model misses (BENCH: a second separable term, cross-talk
#              between the Bayer planes, flicker, stray light, stuck pixels)
#   held-out   the 250 validation photographs (`simulate --seed 1 --only val`) through it; the first
#              four are the user's captures and are not scored
#   references Tikhonov pictures of those four with the camera's own 3 %-error calibration at lambda
#              1e-3, written in linear light and min-max stretched to 8 bits, as FlatNet's rec_*
#   recovered  `calibrate --references` from the four pairs (geometry only, with the references'
#              lambda), then the shipped transpose model adapted through that calibration for MINUTES
#   truth      the same adaptation through the twin's own simulator and calibration, without the bench
# Usage: scripts/twin_check.sh [RUNS_DIR] [PHOTOS_DIR]   (MINUTES=20; each job on one thread)
# Resumable: what exists is reused. Prints both paths' held-out scores.
set -euo pipefail
cd "$(dirname "$0")/.."
runs=${1:-$HOME/flatnet-runs/twin}
photos=$(cd "${2:-../shared/data/images/train}" && pwd)
minutes=${MINUTES:-20}
bench=${BENCH:-"crosstalk: 0.1, second_term: 0.04, flicker: 0.03, stray_light: 0.01, hot_pixels: 100"}
repo=$PWD
flatnet=${FLATNET:-$repo/build/flatnet}
mkdir -p "$runs" && cd "$runs"
[ -f cam/camera.yaml ] || {
  "$flatnet" mask camera --random-codes 11 --centring level --out cam > /dev/null
  echo "bench: {$bench}" >> cam/camera.yaml
}
[ -f heldout/val_meas.txt ] ||
  "$flatnet" simulate --images "$photos" --camera cam/camera.yaml --seed 1 --only val --out heldout > /dev/null
# The user's four captures and someone's Tikhonov pictures of them.
if [ ! -f references.txt ]; then
  mkdir -p refs
  head -4 heldout/val_meas.txt | while read -r f; do cp "heldout/$f" refs/; done
  (grep -v '^bench' cam/camera.yaml; echo "display_gamma: 1") > cam/camera-linear.yaml
  "$flatnet" recon --method tikhonov --camera cam/camera-linear.yaml --lambda 1e-3 --input refs --out refs-tik \
    > /dev/null 2>&1
  /usr/bin/python3 - << 'EOF'
import os
import numpy as np
from PIL import Image
os.makedirs("refs-ref", exist_ok=True)
for name in sorted(f for f in os.listdir("refs-tik") if f.endswith(".png")):
    a = np.asarray(Image.open("refs-tik/" + name).convert("RGB"), dtype=np.float64)
    a = (a - a.min()) / (a.max() - a.min()) * 255
    Image.fromarray(np.round(a).astype(np.uint8)).save("refs-ref/" + name)
EOF
  ls refs | sed 's|^|refs/|' > captures.txt
  ls refs-ref/*.png | sed 's|^\./||' > references.txt
fi
# What the user knows: the geometry, and the lambda of the pictures they hold.
grep -v -E '^(calibration|noise_gain|noise_floor|dark|bench|rig|tikhonov_lambda):' cam/camera.yaml > geometry.yaml
echo "tikhonov_lambda: 0.001" >> geometry.yaml
[ -f cal/camera.yaml ] || {
  mkdir -p cal
  "$flatnet" calibrate --references --meas-list captures.txt --gt-list references.txt --root . \
    --camera geometry.yaml --out cal/calib.mat --compact > cal.log 2>&1
}
mkdir -p truth
grep -v '^bench' cam/camera.yaml | sed -e "s|^calibration: calib.mat|calibration: $runs/cam/calib.mat|" \
  -e "s|^rig: rig.mat|rig: $runs/cam/rig.mat|" > truth/camera.yaml
tail -n +5 heldout/val_meas.txt | sed 's|^|heldout/|' > scored_meas.txt

adapt() {  # NAME CAMERA
  local run=$runs/adapt-$1
  if [ ! -f "$run/model.flatnet" ]; then
    (cd "$repo" && "$flatnet" train --config configs/sim_transpose.yaml --init-from models/flatnet-sim-transpose.flatnet \
      --reinit inversion --set "data.camera=$2" --set "train.minutes=$minutes" --threads 1 --out "$run") > "$run.log" 2>&1
  fi
  [ -d "rec-$1" ] || "$flatnet" infer --model "$run/model.flatnet" --input scored_meas.txt --out "rec-$1" > /dev/null 2>&1
  [ -f "rec-$1/metrics.csv" ] || "$flatnet" eval --gt heldout/gt --out "rec-$1" --niqe none > "eval-$1.log" 2>&1
  echo "$1: $(grep -i -m1 "psnr" "eval-$1.log")"
}
adapt truth "$runs/truth/camera.yaml"
adapt recovered "$runs/cal/camera.yaml"
