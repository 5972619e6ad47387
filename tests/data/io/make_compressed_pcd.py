#!/usr/bin/env python3
"""Writes organised_compressed.pcd: a 4x3 organised cloud, DATA binary_compressed.

Independent of the C++ code on purpose (its own greedy LZF compressor), so the
fixture cross-checks the reader. Run from this folder; the output is committed.
"""
import math
import struct

W, H = 4, 3
N = W * H
nan = float("nan")
# fields: x y z _ (4 padding bytes) rgb normal_x normal_y normal_z
pts, nrm, rgb = [], [], []
for i in range(N):
    if i in (1, 6):  # missing pixels
        pts.append((nan, nan, nan))
    else:
        pts.append((0.5 * i, -0.25 * i, 1.0 + i))
    nrm.append((0.0, 0.0, 1.0))
    rgb.append(((10 * i) << 16) | ((20 * i) << 8) | (255 - i))

raw = b"".join(struct.pack("<f", p[0]) for p in pts)
raw += b"".join(struct.pack("<f", p[1]) for p in pts)
raw += b"".join(struct.pack("<f", p[2]) for p in pts)
raw += b"\xab\xcd\xef\x01" * N
raw += b"".join(struct.pack("<I", c) for c in rgb)
for k in range(3):
    raw += b"".join(struct.pack("<f", n[k]) for n in nrm)


def lzf_compress(data):
    out = bytearray()
    lit = bytearray()
    table = {}
    i = 0

    def flush():
        nonlocal lit
        while lit:
            chunk, lit = lit[:32], lit[32:]
            out.append(len(chunk) - 1)
            out.extend(chunk)

    while i < len(data):
        key = data[i:i + 3]
        ref = table.get(key) if len(key) == 3 else None
        table[key] = i
        if ref is not None and 0 < i - ref <= 8192:
            length = 0
            while i + length < len(data) and data[ref + length] == data[i + length] and length < 264:
                length += 1
            if length >= 3:
                flush()
                off = i - ref - 1
                l = length - 2
                if l < 7:
                    out.append((l << 5) | (off >> 8))
                else:
                    out.append((7 << 5) | (off >> 8))
                    out.append(l - 7)
                out.append(off & 0xFF)
                i += length
                continue
        lit.append(data[i])
        i += 1
    flush()
    return bytes(out)


comp = lzf_compress(raw)
header = (
    "# .PCD v0.7 - Point Cloud Data file format\n"
    "VERSION 0.7\n"
    "FIELDS x y z _ rgb normal_x normal_y normal_z\n"
    "SIZE 4 4 4 1 4 4 4 4\n"
    "TYPE F F F U F F F F\n"
    "COUNT 1 1 1 4 1 1 1 1\n"
    f"WIDTH {W}\nHEIGHT {H}\n"
    "VIEWPOINT 0 0 0 1 0 0 0\n"
    f"POINTS {N}\n"
    "DATA binary_compressed\n"
).encode()
with open("organised_compressed.pcd", "wb") as f:
    f.write(header + struct.pack("<II", len(comp), len(raw)) + comp)
print(len(raw), "->", len(comp))
