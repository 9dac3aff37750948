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

mkdir -p "$out/fp32" "$out/opencv"
for pair in transpose="$transpose" calibfree="$calibfree"; do
  name=${pair%%=*} file=${pair#*=}
  [ -d "$out/fp32/$name" ] || "$bin" infer --precision fp32 --model "$file" --input "$heldout/val_meas.txt" --out "$out/fp32/$name"
  [ -f "$out/$name.onnx" ] || "$bin" export --model "$file" --onnx "$out/$name.onnx"
  [ -d "$out/opencv/$name" ] || "$bin" infer --engine opencv --model "$out/$name.onnx" --input "$heldout/val_meas.txt" --out "$out/opencv/$name"
done
echo "== held-out in fp32 (LibTorch)"
"$bin" eval --niqe none --gt "$heldout/gt" --out "$out/fp32" | tee "$out/fp32/table.txt"
echo "== held-out through OpenCV DNN (fp32)"
"$bin" eval --niqe none --gt "$heldout/gt" --out "$out/opencv" | tee "$out/opencv/table.txt"
echo "== OpenCV DNN against LibTorch, 8-bit codes"
for name in transpose calibfree; do
  /usr/bin/python3 - "$out/fp32/$name" "$out/opencv/$name" "$name" <<'EOF'
import pathlib, sys
import numpy as np, skimage.io
a_dir, b_dir, name = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]), sys.argv[3]
over, total, worst = 0, 0, 0
for a_path in sorted(a_dir.glob("*.png")):
    a = skimage.io.imread(a_path).astype(np.int32)
    b = skimage.io.imread(b_dir / a_path.name).astype(np.int32)
    d = np.abs(a - b)
    over += int((d > 1).sum()); total += d.size; worst = max(worst, int(d.max()))
print(f"{name}: {100.0 * over / total:.3f} % of the 8-bit values differ by more than one code, at most {worst}")
EOF
done
echo "== held-out mean PSNR dB / SSIM to three places: bf16 (LibTorch), fp32 (LibTorch), fp32 (OpenCV DNN)"
for table in heldout fp32 opencv; do
  awk -F, -v t="$table" 'NR > 1 && $2 ~ /^(transpose|calibfree)$/ { n[$2]++; p[$2] += $3; s[$2] += $4 }
    END { for (m in n) printf "%-8s %-10s %.3f / %.4f\n", t, m, p[m] / n[m], s[m] / n[m] }' "$out/$table/metrics.csv" | sort -k2
done
"$bin" report inversion --models transpose="$transpose",calibfree="$calibfree" --out "$out/inversion"
