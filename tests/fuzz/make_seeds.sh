#!/usr/bin/env bash
# Writes the fuzz harnesses' seed corpora (tests/fuzz/corpus/HARNESS/), small files of every kind
# the readers take, from a tiny camera (32-pixel scenes): what flatnet writes (a model file, a
# checkpoint, ONNX, a torch.save state dict, config.yaml, camera files, log.csv and val.csv) and what
# other tools write (.mat by SciPy and by matio as v7.3, PNG and TIFF by Pillow, torch.save by
# PyTorch: tests/data).
# Usage: tests/fuzz/make_seeds.sh [FLATNET_BINARY]   (needs /usr/bin/python3 with SciPy and Pillow)
set -euo pipefail
cd "$(dirname "$0")/../.."
flatnet=$(realpath "${1:-build/flatnet}")
py=/usr/bin/python3
corpus=tests/fuzz/corpus
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
rm -rf "$corpus"
for h in safetensors model_file checkpoint torch_file onnx yaml mat image dataset_lists csv_log calibration; do
  mkdir -p "$corpus/fuzz_$h"
done

# The tiny camera's rig and photographs, and the small .mat, PNG and TIFF seeds, by Python.
"$py" - "$tmp" "$corpus" <<'PY'
import sys, numpy as np, scipy.io
from PIL import Image
tmp, corpus = sys.argv[1], sys.argv[2]
rng = np.random.default_rng(1)
rig = {}
for c in ("b", "gb", "gr", "r"):
    rig["PhiL_" + c] = (rng.random((64, 32)) > 0.5) * 0.06
    rig["PhiR_" + c] = (rng.random((80, 32)) > 0.5) * 0.06
    rig["gain_" + c] = np.ones((1, 1))
rig.update(vig_rows=np.linspace(1e-4, 2e-4, 64)[None], vig_cols=np.linspace(1e-4, 2e-4, 80)[None],
           full_well=np.full((1, 1), 40000.0), read_noise=np.full((1, 1), 4.0), dark=np.full((1, 1), 0.02),
           adc_bits=np.full((1, 1), 10.0))
scipy.io.savemat(f"{tmp}/rig.mat", rig)
import os
os.makedirs(f"{tmp}/photos")
for i in range(16):
    Image.fromarray((rng.random((32, 32, 3)) * 255).astype(np.uint8)).save(f"{tmp}/photos/p{i}.png")
# .mat as SciPy writes it: a calibration's names, small; one compressed, one with a struct and text.
small = {"P1b": rng.standard_normal((6, 4)), "Q1b": rng.standard_normal((7, 4)), "adc_bits": np.full((1, 1), 10.0)}
scipy.io.savemat(f"{corpus}/fuzz_mat/calib_small.mat", small)
# Calibrations for fuzz_calibration's tiny camera (12x14 planes, 8-pixel scenes), as SciPy writes
# them: full factors, and a compact shift-structured file (profiles 16 and 18 samples at +-0.5).
full = {}
for c in ("b", "gb", "gr", "r"):
    full["P1" + c] = rng.random((12, 8)) * 0.01
    full["Q1" + c] = rng.random((14, 8)) * 0.01
scipy.io.savemat(f"{corpus}/fuzz_calibration/full.mat", full)
scipy.io.savemat(f"{corpus}/fuzz_calibration/compact.mat",
                 {"profile_rows": rng.random((4, 16)), "profile_cols": rng.random((4, 18)),
                  "shift_rows": np.array([[0.5]]), "shift_cols": np.array([[-0.5]])})
scipy.io.savemat(f"{corpus}/fuzz_mat/compressed.mat", small, do_compression=True)
scipy.io.savemat(f"{corpus}/fuzz_mat/mixed.mat", {"s": {"a": np.arange(3.0)}, "t": "text", "i": np.int16([[1, 2]])})
# Captures: 16-bit single-channel PNG and TIFF (the first byte picks the extension), an 8-bit RGB PNG.
raw = (rng.random((16, 20)) * 65535).astype(np.uint16)
def save(name, first, image, **kw):
    path = f"{tmp}/{name}"
    image.save(path, **kw)
    with open(path, "rb") as f, open(f"{corpus}/fuzz_image/{name}", "wb") as out:
        out.write(bytes([first]) + f.read())
save("raw16.png", 0, Image.fromarray(raw))
save("raw16.tif", 1, Image.fromarray(raw))
save("photo8.png", 0, Image.fromarray((rng.random((8, 8, 3)) * 255).astype(np.uint8)))
PY
# v7.3 (HDF5) calibrations as matio writes MATLAB's -v7.3 layout (tests/fuzz/make_v73_seed.c).
cc -O1 tests/fuzz/make_v73_seed.c -o "$tmp/make_v73_seed" $(pkg-config --cflags --libs matio)
"$tmp/make_v73_seed" "$corpus/fuzz_calibration/full73.mat"
cp "$corpus/fuzz_calibration/full73.mat" "$corpus/fuzz_mat/v73.mat"
# A compressed variable that inflates 500-fold (tests/data/hostile/make_zip_bomb.py, issue 113).
python3 tests/data/hostile/make_zip_bomb.py "$corpus/fuzz_mat/bomb.mat" 256
cp "$corpus/fuzz_mat/bomb.mat" "$corpus/fuzz_calibration/bomb.mat"

cp tests/data/torch_save/*.pt "$corpus/fuzz_torch_file/"
cp tests/data/cameras/tiny.yaml "$tmp/camera.yaml"
echo "rig: rig.mat" >> "$tmp/camera.yaml"
"$flatnet" simulate --images "$tmp/photos" --camera "$tmp/camera.yaml" --size 32 --val-fraction 0.25 --seed 3 \
  --out "$tmp/ds" > /dev/null
"$flatnet" train --config configs/sim_transpose.yaml --set data.source=dataset \
  --set data.light.exposure_probability=0 --set data.light.lamp_probability=0 --set "data.dataset=$tmp/ds" \
  --set "data.camera=$tmp/camera.yaml" --set model.unet.width=2 --set model.level_input=false --set model.inversion.init=random --set train.crop=0 \
  --set discriminator.width=2 --set train.iterations=2 --set train.val_every=2 --out "$tmp/run" > "$tmp/train.log" 2>&1 || { cat "$tmp/train.log"; exit 1; }
"$flatnet" export --model "$tmp/run/model.flatnet" --onnx "$corpus/fuzz_onnx/tiny.onnx" > /dev/null
"$flatnet" export --model "$tmp/run/model.flatnet" --state-dict --out "$corpus/fuzz_torch_file/flatnet_state_dict.pt" > /dev/null

cp "$tmp/run/model.flatnet" "$corpus/fuzz_model_file/tiny.flatnet"
cp "$tmp/run/model.flatnet" "$corpus/fuzz_safetensors/tiny.flatnet"
cp "$tmp/run/latest.ckpt" "$corpus/fuzz_checkpoint/latest.ckpt"
cp "$tmp/run/config.yaml" "$corpus/fuzz_yaml/config.yaml"
cp tests/data/cameras/tiny.yaml "$corpus/fuzz_yaml/tiny.yaml"
cp configs/cameras/sim_level.yaml "$corpus/fuzz_yaml/camera.yaml"
# A camera file with every optional section: a bench, hot pixels and a colour mix.
cat > "$corpus/fuzz_yaml/camera_sections.yaml" <<'YAML'
name: sections
raw_height: 32
raw_width: 32
crop: [0, 0, 12, 14]
scene_size: 8
hot_pixels: [[1, 2], [30, 31]]
colour_mix: [[0.1, 0.1, 0.8], [0.05, 0.9, 0.05], [0.05, 0.9, 0.05], [0.8, 0.1, 0.1]]
bench: {crosstalk: 0.2, mask_rotation: 0.01, second_term: 0.1, flicker: 0.05, stray_light: 0.02, hot_pixels: 3, display_shift: 1, display_scale: 1.05}
YAML
cp "$tmp/run/val.csv" "$corpus/fuzz_csv_log/val.csv"
cp "$tmp/run/log.csv" "$corpus/fuzz_csv_log/log.csv"
printf 'meas/p0.png\nmeas/p1.png\n\0gt/p0.png\ngt/p1.png\n' > "$corpus/fuzz_dataset_lists/lists"
du -sh "$corpus"/* | sed 's/^/make_seeds: /'
