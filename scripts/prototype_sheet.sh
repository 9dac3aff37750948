#!/usr/bin/env bash
# FlatNet's real prototype, side by side (the README's first picture): FlatNet's own Tikhonov
# (rec_*.png), flatnet's Tikhonov with the calibration identified from them
# (configs/cameras/flatnet_prototype/), flatnet's model for the prototype without the capture's
# data-consistency step (infer --data-consistency off), the model as it runs (the shipped prototype model
# applies the step, c 10, blur 1, unless told otherwise), and, on fc_8 alone, FlatNet's own network
# trained on real captures (flatnet_r_8.png: FlatNet published no other).
#   scripts/prototype_sheet.sh [MODEL] [OUT]
# MODEL: models/flatnet-prototype-transpose.flatnet; OUT: a folder (default /tmp/prototype_sheet),
# which gets tikhonov/, network/ (the step off) and model/ (with camera_fit.csv) and sheet.png, and prints
# colour and detail per unit of luma on fc_8 against FlatNet-R's (scripts/colour_detail.py). Needs ../shared/data/flatnet
# (FLATNET_DATA: another folder with fc_6..9.png and rec_6..9.png).
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-models/flatnet-prototype-transpose.flatnet}
out=${2:-/tmp/prototype_sheet}
data=${FLATNET_DATA:-../shared/data/flatnet}
flatnet=${FLATNET:-build/flatnet}
camera=configs/cameras/flatnet_prototype/camera.yaml
for i in 6 7 8 9; do
  [ -f "$data/fc_$i.png" ] && [ -f "$data/rec_$i.png" ] || { echo "prototype_sheet: $data lacks fc_$i.png or rec_$i.png" >&2; exit 2; }
done
mkdir -p "$out/captures"
for i in 6 7 8 9; do cp "$data/fc_$i.png" "$out/captures/"; done
"$flatnet" recon --method tikhonov --camera "$camera" --input "$out/captures" --out "$out/tikhonov" --require-fit --force
"$flatnet" infer --model "$model" --input "$out/captures" --out "$out/network" --require-fit --force \
  --data-consistency off
"$flatnet" infer --model "$model" --input "$out/captures" --out "$out/model" --require-fit --force
/usr/bin/python3 - "$data" "$out" <<'PY'
import sys
from PIL import Image, ImageDraw
data, out = sys.argv[1], sys.argv[2]
columns = [("FlatNet's Tikhonov", lambda i: f"{data}/rec_{i}.png"),
           ("flatnet Tikhonov", lambda i: f"{out}/tikhonov/fc_{i}.png"),
           ("flatnet network alone", lambda i: f"{out}/network/fc_{i}.png"),
           ("flatnet model (+ capture)", lambda i: f"{out}/model/fc_{i}.png"),
           ("FlatNet-R (fc_8 only)", lambda i: f"{data}/flatnet_r_8.png" if i == 8 else None)]
size, pad, head = 256, 4, 22
sheet = Image.new("RGB", (len(columns) * (size + pad) + pad, head + 4 * (size + pad) + pad), "white")
draw = ImageDraw.Draw(sheet)
for c, (label, path) in enumerate(columns):
    draw.text((pad + c * (size + pad) + 6, 5), label, fill="black")
    for r, i in enumerate([6, 7, 8, 9]):
        if path(i) is None:
            continue
        image = Image.open(path(i)).convert("RGB").resize((size, size))
        sheet.paste(image, (pad + c * (size + pad), head + pad + r * (size + pad)))
sheet.save(f"{out}/sheet.png")
print(f"wrote {out}/sheet.png")
PY
/usr/bin/python3 scripts/colour_detail.py "$data/flatnet_r_8.png" "$out/network/fc_8.png" "$out/model/fc_8.png" \
  "$data/rec_8.png"
