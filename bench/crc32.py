"""CRC-32 throughput: the package's (apcg_core/io/crc.py: ISA-L's where installed) against zlib's.

    .venv/bin/python bench/crc32.py [--mb 256] [--repeats 5]

Every CRC `apcg generate` takes of the clouds it writes (about 48 bytes a point: 0.67 GB for
the 102,400-cloud grid of docs/SCALE.md) goes through the package's function; this times both on
the same random bytes, whole and in the writer's block-sized pieces (1.7 MB), best of
``--repeats``, one thread, and checks that they agree.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import zlib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.io.crc import crc32  # noqa: E402


def best(f, data, piece: int, repeats: int) -> tuple[float, int]:
    times, crc = [], 0
    view = memoryview(data)
    for _ in range(repeats):
        t = time.perf_counter()
        crc = 0
        for i in range(0, len(data), piece):
            crc = f(view[i:i + piece], crc)
        times.append(time.perf_counter() - t)
    return min(times), crc


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mb", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    data = os.urandom(args.mb << 20)
    print(f"package crc32: {crc32.__module__}.{crc32.__name__}")
    for piece in (len(data), 1_700_000):
        tz, cz = best(zlib.crc32, data, piece, args.repeats)
        tp, cp = best(crc32, data, piece, args.repeats)
        if cz != cp:
            raise SystemExit(f"the two CRCs differ: {cz:#x} {cp:#x}")
        print(f"pieces of {piece:>11,} B: zlib {len(data) / tz / 1e9:5.2f} GB/s, package "
              f"{len(data) / tp / 1e9:5.2f} GB/s ({tz / tp:.1f} x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
