#!/usr/bin/env bash
# A twin of FlatNet's prototype (issue 90 #5): a camera a user knows only by four captures and
# someone's Tikhonov pictures of them, whose captures hold light the separable model misses. The whole
# path is scored on held-out photographs through it, against the same path with the twin's truth.
#   truth      the prototype as flatnet identified it (configs/cameras/flatnet_prototype: calibration,
#              open light, noise), in linear light
#   held-out   the 250 validation photographs (`simulate --seed 1 --only val --exposure 0.3`, the
#              prototype's levels) through it, then light the separable model misses added to each raw
#              frame (scripts/missed_light.py: the pixels' gain pattern, a glow, stuck pixels); the
#              first four are the user's captures and are not scored
#   references Tikhonov pictures of those four with the true calibration, in linear light, min-max
#              stretched to 8 bits as FlatNet's rec_*
#   white      one capture of a uniform white scene at 0.15 of the display's white (below full scale),
#              with the same missed light: it sets the calibration's light unit (--white-capture)
#   recovered  `calibrate --references` from the four pairs and the geometry alone (the light unit from
#              its prior on the scenes, --scene-light), then the shipped transpose model adapted through
#              that calibration for STEPS steps
#   recovered-white  the same with the white capture (`--white-capture`: the light unit measured)
#   truth path the same adaptation through the true camera file
# Usage: scripts/twin_check.sh [RUNS_DIR] [PHOTOS_DIR]   (STEPS=800, THREADS=2)
# Resumable: what exists is reused. Prints both paths' held-out scores.
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$PWD
runs=${1:-$HOME/flatnet-runs/twinp}
photos=$(cd "${2:-../shared/data/images/train}" && pwd)
steps=${STEPS:-800}
threads=${THREADS:-2}
flatnet=${FLATNET:-$repo/build/flatnet}
prototype=$repo/configs/cameras/flatnet_prototype
mkdir -p "$runs/truth" && cd "$runs"
grep -v -E '^(display_gamma|# The references|# is v\^1.25|# docs/own-camera.md "The ref)' "$prototype/camera.yaml" |
  sed -e "s|^calibration: .*|calibration: \"$prototype/calib.mat\"|" -e 's/^name: .*/name: "twinp"/' > truth/camera.yaml
if [ ! -f heldout/missed.done ]; then
  "$flatnet" simulate --images "$photos" --camera truth/camera.yaml --seed 1 --only val --exposure 0.3 \
    --out heldout --force > /dev/null
  /usr/bin/python3 "$repo/scripts/missed_light.py" heldout/meas && touch heldout/missed.done
fi
if [ ! -f references.txt ]; then
  mkdir -p refs
  head -4 heldout/val_meas.txt | while read -r f; do cp "heldout/$f" refs/; done
  (cat truth/camera.yaml; echo "display_gamma: 1") > truth/linear.yaml
  "$flatnet" recon --method tikhonov --camera truth/linear.yaml --input refs --out refs-tik > /dev/null 2>&1
  /usr/bin/python3 "$repo/scripts/camera_twin.py" stretch refs-tik refs-ref
  ls refs | sed 's|^|refs/|' > captures.txt
  ls refs-ref/*.png > references.txt
fi
if [ ! -f white/missed.done ]; then
  mkdir -p whiteimg
  /usr/bin/python3 -c "from PIL import Image; Image.new('RGB', (256, 256), (255, 255, 255)).save('whiteimg/white.png')"
  "$flatnet" simulate --images whiteimg --camera truth/camera.yaml --seed 1 --exposure 0.15 --out white --force > /dev/null
  /usr/bin/python3 "$repo/scripts/missed_light.py" white/meas && touch white/missed.done
fi
[ -f calw/camera.yaml ] || {
  mkdir -p calw
  "$flatnet" calibrate --references --meas-list captures.txt --gt-list references.txt --root . \
    --camera "$repo/configs/cameras/flatnet_prototype_level.yaml" --out calw/calib.mat --compact \
    --white-capture white/meas/white.png --white-light 0.15 > calw.log 2>&1
}
[ -f cal/camera.yaml ] || {
  mkdir -p cal
  "$flatnet" calibrate --references --meas-list captures.txt --gt-list references.txt --root . \
    --camera "$repo/configs/cameras/flatnet_prototype_level.yaml" --out cal/calib.mat --compact > cal.log 2>&1
}
tail -n +5 heldout/val_meas.txt | sed 's|^|heldout/|' > scored_meas.txt

adapt() {  # NAME CAMERA
  local run=$runs/adapt-$1
  [ -f "$run/model.flatnet" ] ||
    (cd "$repo" && "$flatnet" train --config configs/prototype_transpose.yaml --init-from models/flatnet-sim-transpose.flatnet \
      --reinit inversion --set "data.camera=$2" --set "train.iterations=$steps" --threads "$threads" --out "$run") \
      > "$run.log" 2>&1
  [ -d "rec-$1" ] || "$flatnet" infer --model "$run/model.flatnet" --input scored_meas.txt --out "rec-$1" > /dev/null 2>&1
  [ -f "eval-$1.log" ] || "$flatnet" eval --gt heldout/gt --out "rec-$1" --niqe none > "eval-$1.log" 2>&1
  echo "$1: $(grep "^rec-$1 " "eval-$1.log")"
}
adapt truth "$runs/truth/camera.yaml"
adapt recovered "$runs/cal/camera.yaml"
adapt recovered-white "$runs/calw/camera.yaml"
