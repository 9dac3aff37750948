#!/usr/bin/env bash
# A sheet to judge detail by eye (issue 112): fur, feathers of grass and leaves, beside the truth.
# Six held-out photographs (a Siamese cat, a tiger in grass, a Bernese dog, a rabbit in grass, a
# butterfly on leaves, a cabbage) reconstructed by each model, then `flatnet eval` on them alone:
# OUT/recon/sheet.png (truth first, one column per model) and OUT/recon/metrics.csv.
# Usage: scripts/detail_sheet.sh OUT NAME=MODEL [NAME=MODEL ...]
# Environment: HELDOUT (default data/eval/heldout, scripts/make_eval_sets.sh), FLATNET.
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -ge 2 ] || { echo "usage: scripts/detail_sheet.sh OUT NAME=MODEL [NAME=MODEL ...]" >&2; exit 2; }
out=$1
shift
bin=${FLATNET:-$PWD/build/flatnet}
heldout=${HELDOUT:-data/eval/heldout}
[ -f "$heldout/val_meas.txt" ] || { echo "detail_sheet: $heldout missing (run scripts/make_eval_sets.sh)" >&2; exit 2; }
[ "$(realpath -m "$out")" != "$(realpath "$heldout")" ] || { echo "detail_sheet: OUT is the held-out set" >&2; exit 2; }
mkdir -p "$out/gt" "$out/recon"
grep -E '7580_tiger|Bernese_mountain_dog|Siamese_cat|wood_rabbit|ringlet|inet_n07714571_head_cabbage' \
  "$heldout/val_meas.txt" | sed "s|^|$(realpath "$heldout")/|" > "$out/meas.txt"
[ "$(wc -l < "$out/meas.txt")" -eq 6 ] || { echo "detail_sheet: the six photographs are not all in $heldout" >&2; exit 2; }
while read -r m; do cp "$(dirname "$(dirname "$m")")/gt/$(basename "$m")" "$out/gt/"; done < "$out/meas.txt"
for pair in "$@"; do
  name=${pair%%=*} model=${pair#*=}
  [[ $name =~ ^[A-Za-z0-9._+-]+$ && -f $model ]] || { echo "detail_sheet: give NAME=MODEL, got '$pair'" >&2; exit 2; }
  "$bin" infer --model "$model" --input "$out/meas.txt" --out "$out/recon/$name" --threads 1 > "$out/$name.log" 2>&1
done
"$bin" eval --gt "$out/gt" --out "$out/recon" --sheet-rows 6 --threads 1 | tail -n "$(( $# + 3 ))"
