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
# colour and detail per unit of luma and the tone-matched mid-band detail on fc_8 against FlatNet-R's
# (scripts/colour_detail.py). The sheet's last row is fc_8 again, each picture's histogram matched per
# channel to FlatNet-R's, so that tone does not decide what looks sharp. Needs ../shared/data/flatnet
# (FLATNET_DATA: another folder with fc_6..9.png and rec_6..9.png). CAMERA: another camera file of the
# prototype for the Tikhonov column (a calibration identified another way; default the shipped one).
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-models/flatnet-prototype-transpose.flatnet}
out=${2:-/tmp/prototype_sheet}
data=${FLATNET_DATA:-../shared/data/flatnet}
flatnet=${FLATNET:-build/flatnet}
camera=${CAMERA:-configs/cameras/flatnet_prototype/camera.yaml}
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
import numpy as np
from PIL import Image, ImageDraw
from skimage.exposure import match_histograms
data, out = sys.argv[1], sys.argv[2]
columns = [("FlatNet's Tikhonov", lambda i: f"{data}/rec_{i}.png"),
           ("flatnet Tikhonov", lambda i: f"{out}/tikhonov/fc_{i}.png"),
           ("flatnet network alone", lambda i: f"{out}/network/fc_{i}.png"),
           ("flatnet model (+ capture)", lambda i: f"{out}/model/fc_{i}.png"),
           ("FlatNet-R (fc_8 only)", lambda i: f"{data}/flatnet_r_8.png" if i == 8 else None)]
size, pad, head = 256, 4, 22
rows = [6, 7, 8, 9, "8m"]  # "8m": fc_8 with its tone matched to FlatNet-R's
flatnet_r = np.asarray(Image.open(f"{data}/flatnet_r_8.png").convert("RGB").resize((size, size)))
sheet = Image.new("RGB", (len(columns) * (size + pad) + pad, head + len(rows) * (size + pad) + pad), "white")
draw = ImageDraw.Draw(sheet)
for c, (label, path) in enumerate(columns):
    draw.text((pad + c * (size + pad) + 6, 5), label, fill="black")
    for r, i in enumerate(rows):
        matched = i == "8m"
        if path(8 if matched else i) is None:
            continue
        image = Image.open(path(8 if matched else i)).convert("RGB").resize((size, size))
        if matched:
            image = Image.fromarray(np.clip(match_histograms(np.asarray(image), flatnet_r, channel_axis=-1),
                                            0, 255).astype(np.uint8))
        sheet.paste(image, (pad + c * (size + pad), head + pad + r * (size + pad)))
draw.text((pad + 6, head + pad + 4 * (size + pad) + 4), "fc_8, tone matched to FlatNet-R", fill="white")
sheet.save(f"{out}/sheet.png")
print(f"wrote {out}/sheet.png")
PY
/usr/bin/python3 scripts/colour_detail.py "$data/flatnet_r_8.png" "$out/network/fc_8.png" "$out/model/fc_8.png" \
  "$out/tikhonov/fc_8.png" "$data/rec_8.png"
