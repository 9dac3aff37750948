#!/usr/bin/env bash
# Makes the held-out evaluation sets behind the README's FlatNet tables, from the shared photographs:
#   heldout  the 250 held-out display captures (the split and noise of `flatnet simulate --seed 1`,
#            the same captures as data/sim/val_*.txt)
#   dim      the same scenes at a third of the display's light (gt/ shows the dim scene)
#   lamp     the same scenes with a small lamp 20x brighter than display white
# Usage: scripts/make_eval_sets.sh [PHOTOS_DIR] [OUT_DIR]   (defaults: ../shared/data/images/train data/eval)
set -euo pipefail
cd "$(dirname "$0")/.."
photos=${1:-../shared/data/images/train}
out=${2:-data/eval}
flatnet=${FLATNET:-build/flatnet}
"$flatnet" simulate --images "$photos" --out "$out/heldout" --seed 1 --only val
"$flatnet" simulate --images "$photos" --out "$out/dim" --seed 1 --only val --exposure 0.33
"$flatnet" simulate --images "$photos" --out "$out/lamp" --seed 1 --only val --lamp --lamp-gain 20
