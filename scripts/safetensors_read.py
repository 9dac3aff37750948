#!/usr/bin/env python3
"""An independent reader of safetensors files (flatnet's model files and checkpoints), written from
the format's specification (https://github.com/huggingface/safetensors, "Format") with nothing but
Python's standard library: no torch, no pickle, nothing in the file is ever run.

    python3 scripts/safetensors_read.py FILE [--json]

Prints each tensor's name, dtype, shape and the sum and sum of squares of its elements, and the
__metadata__ keys (their values with --json). Exits 1, naming the rule, when the file breaks the
specification: header length, JSON, duplicate names, dtype, shape, offsets that do not tile the
byte buffer exactly.
"""
import json
import math
import struct
import sys
import zlib

# dtype -> (struct code, bytes per element); BF16 is the top half of an IEEE float32.
DTYPES = {
    "F64": ("d", 8), "F32": ("f", 4), "F16": ("e", 2), "BF16": (None, 2),
    "I64": ("q", 8), "I32": ("i", 4), "I16": ("h", 2), "I8": ("b", 1),
    "U8": ("B", 1), "BOOL": ("?", 1),
}
MAX_HEADER = 100 * 1000 * 1000  # the specification's limit


class FormatError(Exception):
    pass


def no_duplicates(pairs):
    keys = [k for k, _ in pairs]
    if len(keys) != len(set(keys)):
        raise FormatError("duplicate key in the header")
    return dict(pairs)


def elements(dtype, raw):
    if dtype == "BF16":
        words = struct.unpack("<%dH" % (len(raw) // 2), raw)
        return [struct.unpack("<f", struct.pack("<I", w << 16))[0] for w in words]
    code, size = DTYPES[dtype]
    return list(struct.unpack("<%d%s" % (len(raw) // size, code), raw))


def read(path):
    with open(path, "rb") as f:
        data = f.read()
    if len(data) < 8:
        raise FormatError("shorter than the 8-byte header length")
    (n,) = struct.unpack("<Q", data[:8])
    if n > MAX_HEADER or n > len(data) - 8:
        raise FormatError("header length %d exceeds the limit or the file" % n)
    header_bytes = data[8:8 + n]
    if not header_bytes.startswith(b"{"):
        raise FormatError("header does not start with '{'")
    header = json.loads(header_bytes.decode("utf-8"), object_pairs_hook=no_duplicates)
    metadata = header.pop("__metadata__", {})
    if not all(isinstance(v, str) for v in metadata.values()):
        raise FormatError("__metadata__ values must be strings")
    buffer = data[8 + n:]
    spans = []
    tensors = {}
    for name, info in header.items():
        dtype, shape, (begin, end) = info["dtype"], info["shape"], info["data_offsets"]
        if dtype not in DTYPES:
            raise FormatError("%s: unknown dtype %s" % (name, dtype))
        if not all(isinstance(s, int) and s >= 0 for s in shape):
            raise FormatError("%s: bad shape %r" % (name, shape))
        count = math.prod(shape)
        if end - begin != count * DTYPES[dtype][1]:
            raise FormatError("%s: %d bytes for %d elements of %s" % (name, end - begin, count, dtype))
        spans.append((begin, end, name))
        tensors[name] = (dtype, shape, buffer[begin:end])
    at = 0
    for begin, end, name in sorted(spans):
        if begin != at:
            raise FormatError("%s: starts at %d, expected %d (holes or overlaps)" % (name, begin, at))
        at = end
    if at != len(buffer):
        raise FormatError("the buffer holds %d bytes, the tensors %d" % (len(buffer), at))
    # flatnet's extension: zlib's CRC-32 of the byte buffer (other writers leave it out).
    if "data_crc32" in metadata and int(metadata["data_crc32"], 16) != zlib.crc32(buffer):
        raise FormatError("the byte buffer fails its data_crc32 (damaged file)")
    return metadata, tensors


def main():
    if len(sys.argv) < 2:
        print(__doc__)
        return 2
    try:
        metadata, tensors = read(sys.argv[1])
    except (FormatError, ValueError, KeyError, TypeError) as e:
        print("%s: not a valid safetensors file: %s" % (sys.argv[1], e), file=sys.stderr)
        return 1
    summary = {"metadata": metadata if "--json" in sys.argv else sorted(metadata), "tensors": {}}
    for name, (dtype, shape, raw) in tensors.items():
        values = [float(v) for v in elements(dtype, raw)]
        summary["tensors"][name] = {"dtype": dtype, "shape": shape, "sum": math.fsum(values),
                                    "sum_sq": math.fsum(v * v for v in values)}
    if "--json" in sys.argv:
        print(json.dumps(summary))
    else:
        for name, t in summary["tensors"].items():
            print("%-60s %-5s %-20s sum %.6g" % (name, t["dtype"], t["shape"], t["sum"]))
        print("metadata:", ", ".join(summary["metadata"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
