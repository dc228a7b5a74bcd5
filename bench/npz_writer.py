"""The streamed NPZ writer (``apcg_core.io.clouds.CloudWriter``) on a large output: blocks of
random points spilled, then the zip made, with the kernel copying the spilled arrays into it
(``os.copy_file_range``, the default where the kernel has it) or, with ``--plain``, through
Python block by block (what every other system does). Whole processes, so time them from
outside, e.g.

    /usr/bin/time -v .venv/bin/python bench/npz_writer.py --points 12000000
    /usr/bin/time -v .venv/bin/python bench/npz_writer.py --points 12000000 --plain

It prints the output's size and the seconds spent in the writer (wall and CPU of this
process); the file is written into a temporary directory and removed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    from apcg_core.cloud import PointCloud
    from apcg_core.io.clouds import CloudWriter

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=12_000_000)
    ap.add_argument("--block", type=int, default=1_000_000, help="points a block")
    ap.add_argument("--plain", action="store_true",
                    help="copy through Python (hide os.copy_file_range)")
    args = ap.parse_args()
    if args.plain and hasattr(os, "copy_file_range"):
        del os.copy_file_range
    rng = np.random.default_rng(0)
    block = PointCloud(rng.normal(size=(args.block, 3)), rng.uniform(1, 9, args.block),
                       rng.integers(-9, 9, args.block), rng.integers(-9, 9, args.block),
                       np.zeros(args.block, np.int64))
    with tempfile.TemporaryDirectory(prefix="apcg-npz-writer-") as tmp:
        path = Path(tmp) / "clouds.npz"
        cpu, wall = time.process_time(), time.perf_counter()
        with CloudWriter(path, {"bench": "npz_writer"}) as w:
            for _ in range(args.points // args.block):
                w.write(block)
        out = {"points": args.points, "plain": args.plain, "bytes": path.stat().st_size,
               "writer_wall_s": round(time.perf_counter() - wall, 3),
               "writer_cpu_s": round(time.process_time() - cpu, 3)}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
