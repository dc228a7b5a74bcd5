"""Cost of `apcg evaluate` against the number of pairs (it must scale linearly; 10,000 pairs in
at most 5 minutes), and the effect of subsampling clouds to 2,048 points on the scores.

    .venv/bin/python bench/evaluate_cost.py --data data/cpu [--model DIR] [--pairs 1000,3000,9800]
        [--json bench/results/evaluate_cost.json]
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

from apcg_core.families.cgan import APCGModel  # noqa: E402
from apcg_core.metrics import jsd, mmd  # noqa: E402
from training import evaluate as ev  # noqa: E402
from training.data import DepthDataset  # noqa: E402


def subsampling_effect(model, data, n: int = 200, seed: int = 0) -> dict:
    """MMD / JSD of the largest test clouds, whole against subsampled to 2,048 points."""
    ds = DepthDataset(data, "test")
    sizes = np.diff(ds.offsets)
    idx = np.argsort(sizes)[::-1][:n]  # the clouds subsampling touches most
    res = model.generate(ds.conditions[idx], count=1, seed=seed)
    gen = [c.xyz for c in res.cloud.split(len(idx))]
    d_mmd, d_jsd = [], []
    for k, i in enumerate(idx):
        std = ds.standard_cloud(int(i))
        full = (mmd(std, gen[k]), jsd(std, gen[k], bins=6))
        sub = (mmd(std, gen[k], max_points=2048, seed=seed),
               jsd(std, gen[k], bins=6, max_points=2048, seed=seed))
        if None not in full + sub:
            d_mmd.append(abs(full[0] - sub[0]))
            d_jsd.append(abs(full[1] - sub[1]))
    return {"clouds": len(idx), "largest_points": int(sizes[idx[0]]),
            "over_2048": int((sizes > 2048).sum()),
            "mmd_abs_change_mean": float(np.mean(d_mmd)),
            "mmd_abs_change_max": float(np.max(d_mmd)),
            "jsd_abs_change_mean": float(np.mean(d_jsd)),
            "jsd_abs_change_max": float(np.max(d_jsd))}


def main() -> int:
    from bench_output import emit

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--model")
    ap.add_argument("--pairs", default="1000,3000,9800")
    ap.add_argument("--json")
    args = ap.parse_args()
    model = APCGModel(args.model, runtime="onnx")
    rows = []
    for n in (int(x) for x in args.pairs.split(",")):
        t0 = time.perf_counter()
        rep = ev.evaluate(model, args.data, n_pairs=n, seed=0)
        rows.append({"pairs": rep["pairs"], "seconds": round(time.perf_counter() - t0, 1)})
        print(json.dumps(rows[-1]), flush=True)
    per_pair = np.polyfit([r["pairs"] for r in rows], [r["seconds"] for r in rows], 1)
    out = {"command": "python bench/evaluate_cost.py " + shlex.join(sys.argv[1:]),
           "rows": rows, "seconds_per_pair": float(per_pair[0]),
           "fixed_seconds": float(per_pair[1]),
           "seconds_for_10000": float(np.polyval(per_pair, 10_000)),
           "subsampling": subsampling_effect(model, args.data)}
    emit(out, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
