#!/usr/bin/env python3
"""How well a training run's judged validation (data.val_light: judged) stands for the evaluation sets.

The validation takes the first COUNT held-out photographs (sorted by name, train.val_count) and lights
item i as display (i % 3 == 0), dim (1) or lamp (2). This script reads the per-image scores that
scripts/eval_tables.sh wrote into EVAL/{heldout,dim,lamp}/metrics.csv and prints, per method, the mean
PSNR over those images of each set beside the mean over the whole set.
Usage: scripts/judged_subset.py EVAL [COUNT (default 96)] [SETS_DIR (default data/eval)]"""
import collections
import csv
import statistics
import sys

SETS = ["heldout", "dim", "lamp"]


def main() -> int:
    if len(sys.argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    scores, count = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 96
    sets_dir = sys.argv[3] if len(sys.argv) > 3 else "data/eval"
    with open(f"{sets_dir}/heldout/val_meas.txt") as f:
        names = sorted(line.strip().split("/")[-1] for line in f if line.strip())[:count]
    table = collections.defaultdict(dict)  # method -> set -> (subset mean, subset size, whole-set mean)
    for k, name in enumerate(SETS):
        judged = {n for i, n in enumerate(names) if i % 3 == k}
        subset, whole = collections.defaultdict(list), collections.defaultdict(list)
        with open(f"{scores}/{name}/metrics.csv") as f:
            for row in csv.DictReader(f):
                if not row["psnr"]:  # the ground truth's own row
                    continue
                whole[row["method"]].append(float(row["psnr"]))
                if row["image"] in judged:
                    subset[row["method"]].append(float(row["psnr"]))
        for method, values in subset.items():
            table[method][name] = (statistics.mean(values), len(values), statistics.mean(whole[method]))
    print(f"{'method':22s}" + "".join(f"{s + ': judged (n) / all':>28s}" for s in SETS) + "   mean: judged / all")
    for method, row in sorted(table.items()):
        if len(row) < len(SETS):
            continue
        cells = "".join(f"{row[s][0]:14.2f} ({row[s][1]:2d}) / {row[s][2]:6.2f}" for s in SETS)
        judged_mean = statistics.mean(row[s][0] for s in SETS)
        whole_mean = statistics.mean(row[s][2] for s in SETS)
        print(f"{method:22s}{cells}   {judged_mean:6.2f} / {whole_mean:6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
