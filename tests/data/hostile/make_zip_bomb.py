#!/usr/bin/env python3
"""A MATLAB v5 .mat whose one compressed variable P1b inflates to N x N doubles of zeros (8 N^2 bytes)
from about N^2/128 bytes: the zip bomb of issue 113 (N = 16384: 2 GiB from 2.1 MB). The zlib stream is
written in chunks, so making it needs no more memory than a chunk.
  python3 tests/data/hostile/make_zip_bomb.py OUT.mat [N]"""
import struct
import sys
import zlib


def main(out, n):
    header = b"MATLAB 5.0 MAT-file, a zip bomb (flatnet tests)".ljust(116, b" ")
    header += b"\0" * 8 + struct.pack("<H", 0x0100) + b"IM"
    data_bytes = n * n * 8
    inner = struct.pack("<IIII", 6, 8, 6, 0)  # array flags: mxDOUBLE_CLASS
    inner += struct.pack("<IIii", 5, 8, n, n)  # dimensions
    inner += struct.pack("<II", 1, 3) + b"P1b" + b"\0" * 5  # name
    inner += struct.pack("<II", 9, data_bytes)  # miDOUBLE real part, then the zeros
    z = zlib.compressobj(9)
    parts = [z.compress(struct.pack("<II", 14, len(inner) + data_bytes) + inner)]
    chunk = b"\0" * (1 << 24)
    left = data_bytes
    while left:
        k = min(left, len(chunk))
        parts.append(z.compress(chunk[:k]))
        left -= k
    parts.append(z.flush())
    body = b"".join(parts)
    with open(out, "wb") as f:
        f.write(header + struct.pack("<II", 15, len(body)) + body)  # miCOMPRESSED


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 16384)
