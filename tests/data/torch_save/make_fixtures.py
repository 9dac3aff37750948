#!/usr/bin/python3
"""Writes the torch.save fixtures the C++ reader is tested on (tests/test_torch_file.cpp).

Run once with a Python that has torch (Debian: /usr/bin/python3, python3-torch); the files are
committed so that every machine tests the same bytes. Usage: make_fixtures.py [OUT_DIR]
Each file holds small tensors with known values: t[i] = i (+ 0.5 for floats), reshaped.
"""
import collections
import os
import sys

import torch

out = sys.argv[1] if len(sys.argv) > 1 else os.path.dirname(os.path.abspath(__file__))


def ramp(*shape, dtype=torch.float32):
    n = 1
    for s in shape:
        n *= s
    return (torch.arange(n, dtype=torch.float64) + 0.5).reshape(*shape).to(dtype)


def save(name, obj, legacy=False):
    torch.save(obj, os.path.join(out, name), _use_new_zipfile_serialization=not legacy)


# torch.save(model.state_dict()): an OrderedDict with _metadata, in the zip container.
sd = collections.OrderedDict([("conv.weight", ramp(2, 1, 3, 3)), ("conv.bias", ramp(2)),
                              ("bn.num_batches_tracked", torch.tensor(7))])
sd._metadata = collections.OrderedDict([("", {"version": 1}), ("conv", {"version": 1})])
save("ordered_dict_zip.pt", sd)
# The same in the legacy (pre-1.6) container.
save("ordered_dict_legacy.pt", sd, legacy=True)
# A dict with a single key around a plain dict (the SETITEM case).
save("single_key.pt", {"gen_state_dict": {"w": ramp(3)}})
# DataParallel: every key prefixed with "module.".
save("data_parallel.pt", collections.OrderedDict([("module.w", ramp(2, 2)), ("module.b", ramp(2))]))
# Other storage types, converted to float32 on reading; integers stay integers.
save("dtypes.pt", {"f64": ramp(2, 3, dtype=torch.float64), "f16": ramp(4, dtype=torch.float16),
                   "bf16": ramp(4, dtype=torch.bfloat16), "i64": torch.arange(3), "scalar": torch.tensor(2.5)})
# Views of one storage: an offset slice and a transpose (non-contiguous strides), sharing storage.
base = ramp(4, 5)
save("views.pt", {"rows": base[1:3], "t": base.t(), "col": base[:, 2], "base": base})
save("views_legacy.pt", {"rows": base[1:3], "t": base.t(), "col": base[:, 2], "base": base}, legacy=True)
# A FlatNet-style checkpoint: nested OrderedDicts, optimiser state, numbers, lists, tuples.
gen = collections.OrderedDict([("PhiL", ramp(3, 2)), ("bn.weight", ramp(4))])
opt = {"state": {0: {"step": 3, "exp_avg": ramp(3, 2)}}, "param_groups": [{"lr": 1e-4, "betas": (0.9, 0.999), "params": [0, 1]}]}
save("checkpoint_legacy.pt", {"epoch": 12, "gen_state_dict": gen, "dis_state_dict": collections.OrderedDict([("x", ramp(1))]),
                              "optimizerG_state_dict": opt, "optimizerD_state_dict": opt, "note": None, "ok": True}, legacy=True)
print("wrote fixtures to", out)
