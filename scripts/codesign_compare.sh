#!/usr/bin/env bash
# Co-design against designing the mask first (issue 27, part 2), measured on held-out photographs
# captured through each camera (display captures, dim scenes, a lamp):
#   cameras  mls       the reference camera (configs/cameras/sim_level.yaml)
#            separable the codes learned for Tikhonov (models/masks/separable/codes.mat)
#            codesign  the codes learned with FlatNet (RUNS/codesign-2651/camera)
#            binary    their binary variant (RUNS/codesign-binary-600/camera: 600 more steps with
#                      codes.binary, from the co-designed codes and model; a 0/1 mask to fabricate)
#            codesign-mls  the codes learned with FlatNet from MLS (RUNS/codesign-mls-2651/camera)
#   models   FlatNet trained from scratch for 2651 steps on each camera (the same recipe,
#            configs/sim_transpose.yaml, batch 8, crop 128, cosine); on MLS also the shipped model;
#            at equal wall time, MLS and the separable codes also trained for 54 minutes (the
#            co-design's 2651 steps took 53.5 and 57.7 minutes on the same shared two cores)
#   sets     heldout (the 250 held-out photographs, `flatnet simulate --seed 1 --only val`), dim
#            (--exposure 0.33), lamp (--lamp --lamp-gain 20), as scripts/make_eval_sets.sh
# The runs themselves (commands in docs/masks.md, "Co-design"):
#   RUNS/mls-scratch-2651, RUNS/learned-scratch-40min (2651 steps in its 40 minutes),
#   RUNS/codesign-2651 (codes.learn, started from the separable codes), RUNS/codesign-binary-600
# Usage: scripts/codesign_compare.sh [RUNS_DIR] [PHOTOS_DIR] (CAMERAS="mls separable codesign binary codesign-mls" by default);
# writes RUNS_DIR/codesign_table.md.
# Resumable: simulated sets and reconstructions that exist are reused.
set -euo pipefail
cd "$(dirname "$0")/.."
runs=${1:-$HOME/flatnet-runs}
photos=${2:-../shared/data/images/train}
flatnet=${FLATNET:-$PWD/build/flatnet}

camera_yaml() {  # CAMERA -> its camera.yaml
  case $1 in
    mls) echo "$PWD/configs/cameras/sim_level.yaml" ;;
    separable) echo "$runs/cam-learned/camera.yaml" ;;
    codesign) echo "$runs/codesign-2651/camera/camera.yaml" ;;
    binary) echo "$runs/codesign-binary-600/camera/camera.yaml" ;;
    codesign-mls) echo "$runs/codesign-mls-2651/camera/camera.yaml" ;;
  esac
}
models() {  # CAMERA -> NAME=MODEL ...
  case $1 in
    mls) echo "scratch-2651=$runs/mls-scratch-2651/model.flatnet shipped=$PWD/models/flatnet-sim-transpose.flatnet" \
      "$(optional scratch-54min "$runs/mls-scratch-54min/model.flatnet")" ;;
    separable) echo "scratch-2651=$runs/learned-scratch-40min/model.flatnet" \
      "$(optional scratch-54min "$runs/learned-scratch-54min/model.flatnet")" ;;
    codesign-mls) echo "codesign-2651=$runs/codesign-mls-2651/model.flatnet" ;;
    codesign) echo "codesign-2651=$runs/codesign-2651/model.flatnet" ;;
    binary) echo "binary-2651+600=$runs/codesign-binary-600/model.flatnet" ;;
  esac
}
optional() {  # NAME FILE -> NAME=FILE when the run exists
  if [ -f "$2" ]; then echo "$1=$2"; fi
}
set_flags() {  # SET -> simulate's flags
  case $1 in
    heldout) echo "" ;;
    dim) echo "--exposure 0.33" ;;
    lamp) echo "--lamp --lamp-gain 20" ;;
  esac
}

[ -f "$runs/cam-learned/camera.yaml" ] ||
  "$flatnet" mask camera --codes models/masks/separable/codes.mat --centring level --out "$runs/cam-learned"

echo "| camera | model | set | PSNR dB | SSIM | colour kept | detail kept | NIQE |" > "$runs/codesign_table.md.tmp"
echo "|---|---|---|---|---|---|---|---|" >> "$runs/codesign_table.md.tmp"
for cam in ${CAMERAS:-mls separable codesign binary codesign-mls}; do
  yaml=$(camera_yaml "$cam")
  for set in heldout dim lamp; do
    data=$runs/codesign-eval/$cam/$set
    # shellcheck disable=SC2046
    [ -f "$data/val_meas.txt" ] ||
      "$flatnet" simulate --camera "$yaml" --images "$photos" --out "$data" --seed 1 --only val $(set_flags "$set") > /dev/null
    rec=$runs/codesign-eval/$cam/rec-$set
    [ -d "$rec/tikhonov" ] ||
      "$flatnet" recon --camera "$yaml" --input "$data/val_meas.txt" --out "$rec/tikhonov" > /dev/null
    for entry in $(models "$cam"); do
      name=${entry%%=*} model=${entry#*=}
      [ -d "$rec/$name" ] ||
        "$flatnet" infer --model "$model" --camera "$yaml" --input "$data/val_meas.txt" --out "$rec/$name" > /dev/null
    done
    # Scored again only when a reconstruction folder is newer than the scores.
    if [ ! -f "$rec/metrics.csv" ] || [ -n "$(find "$rec" -mindepth 1 -maxdepth 1 -type d -newer "$rec/metrics.csv")" ]; then
      "$flatnet" eval --gt "$data/gt" --out "$rec" > "$rec.eval.txt" 2>&1
    fi
    # metrics.csv: image,method,psnr,ssim,mean_output,mean_truth,niqe,colour_kept,detail_kept
    grep '^mean,' "$rec/metrics.csv" | grep -v ',ground truth,' | sort -t, -k2,2 |
      while IFS=, read -r _ method psnr ssim _ _ niqe colour detail; do
        printf '| %s | %s | %s | %.2f | %.3f | %.2f | %.2f | %.2f |\n' "$cam" "$method" "$set" "$psnr" "$ssim" "$colour" "$detail" "$niqe"
      done >> "$runs/codesign_table.md.tmp"
  done
done
mv "$runs/codesign_table.md.tmp" "$runs/codesign_table.md"
cat "$runs/codesign_table.md"
