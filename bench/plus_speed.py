"""Milliseconds per cloud of APCG+ models, generation alone (conditions in, clouds out, no file),
batched, onnxruntime, measured one after another in one run on the same conditions.

    .venv/bin/python bench/plus_speed.py --data data/cpu --model NAME=DIR ... [--n 2048]
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.families import load_model  # noqa: E402
from training.data import DepthDataset  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--model", action="append", required=True, metavar="NAME=DIR")
    ap.add_argument("--n", type=int, default=2048)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    ds = DepthDataset(args.data, "test")
    cond = ds.condition_rows(np.arange(min(args.n, len(ds))))
    out = {}
    for spec in args.model:
        name, d = spec.split("=", 1)
        m = load_model(d)
        m.generate(cond[:64])  # warm the runtime
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            m.generate(cond)
            times.append(time.perf_counter() - t0)
        out[name] = round(1e3 * float(np.median(times)) / len(cond), 4)
        print(f"{name}: {out[name]:.4f} ms/cloud", flush=True)
    print(json.dumps({"command": "python bench/plus_speed.py " + shlex.join(sys.argv[1:]),
                      "clouds": len(cond), "ms_per_cloud": out}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
