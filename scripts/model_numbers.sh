#!/usr/bin/env bash
# Every number the docs cite for a pair of FlatNet models, before they are shipped: the three sets
# (scripts/eval_tables.sh: PSNR, SSIM, NIQE, colour and detail kept), the held-out set in fp32
# beside bf16 (the accuracy guard), through OpenCV DNN from the ONNX export (PSNR, and how many 8-bit
# pixels differ from LibTorch's fp32 and by how much), and the thesis's Figure 3.3 (report inversion).
# Usage: scripts/model_numbers.sh OUT TRANSPOSE.flatnet CALIBFREE.flatnet
#   Needs data/eval (scripts/make_eval_sets.sh); resumes from what OUT already holds.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: scripts/model_numbers.sh OUT TRANSPOSE.flatnet CALIBFREE.flatnet}
transpose=${2:?transpose model file}
calibfree=${3:?calibration-free model file}
bin=${FLATNET:-build/flatnet}
heldout=data/eval/heldout

SETS="heldout dim lamp" TV_COUNT=-1 scripts/eval_tables.sh "$out" transpose="$transpose" calibfree="$calibfree"

# The held-out set in fp32 through both engines, one folder so that one `flatnet eval` scores them.
engines=$out/engines
mkdir -p "$engines"
for pair in transpose="$transpose" calibfree="$calibfree"; do
  name=${pair%%=*} file=${pair#*=}
  [ -d "$engines/$name-libtorch" ] || "$bin" infer --precision fp32 --model "$file" --input "$heldout/val_meas.txt" --out "$engines/$name-libtorch"
  [ -f "$out/$name.onnx" ] || "$bin" export --model "$file" --onnx "$out/$name.onnx"
  [ -d "$engines/$name-opencv" ] || "$bin" infer --engine opencv --model "$out/$name.onnx" --input "$heldout/val_meas.txt" --out "$engines/$name-opencv"
done
echo "== held-out in fp32: LibTorch and OpenCV DNN"
"$bin" eval --niqe none --gt "$heldout/gt" --out "$engines" | tee "$engines/table.txt"
# Three places from the scores.json files `flatnet eval` wrote (its tables print two), and how far
# OpenCV's 8-bit pictures are from LibTorch's.
/usr/bin/python3 - "$out/heldout/scores.json" "$engines" <<'EOF'
import json, pathlib, sys
import numpy as np, skimage.io
bf16, engines = json.load(open(sys.argv[1])), pathlib.Path(sys.argv[2])
fp32 = json.load(open(engines / "scores.json"))
for name in ("transpose", "calibfree"):
    rows = [("bf16 LibTorch", bf16[name]), ("fp32 LibTorch", fp32[name + "-libtorch"]),
            ("fp32 OpenCV DNN", fp32[name + "-opencv"])]
    print(name + ": " + ", ".join(f"{label} {s['psnr']:.3f} dB / {s['ssim']:.4f}" for label, s in rows))
    over, total, worst = 0, 0, 0
    for a_path in sorted((engines / (name + "-libtorch")).glob("*.png")):
        a = skimage.io.imread(a_path).astype(np.int32)
        b = skimage.io.imread(engines / (name + "-opencv") / a_path.name).astype(np.int32)
        d = np.abs(a - b)
        over += int((d > 1).sum()); total += d.size; worst = max(worst, int(d.max()))
    print(f"{name}: {100.0 * over / total:.3f} % of OpenCV's 8-bit values differ from LibTorch's"
          f" by more than one code, at most {worst}")
EOF
"$bin" report inversion --models transpose="$transpose",calibfree="$calibfree" --out "$out/inversion"
