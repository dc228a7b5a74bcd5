"""Whether an APCG+ model's hit probabilities are the data's: a reliability table (issue 35,
point 4: where the generated wings come out wider).

For the recognition benchmark's look-alike types and the widebody (A320neo, 737-800, G550,
G650ER, 777-300ER) at random Table 1 conditions beyond 1 km (the benchmark's own condition
plan, ``--seed``), every box cell the model reads: its probability p = sigmoid(logit) and
whether the exact simulator (embree) returned that cell. Per group of cells (all; the outer
ones, |u| > 0.6 of the bounding radius from the centre across the line of sight: the wingtips;
the inner ones): exact returns, the sum of p (what a calibrated model expects), the cells
above the model's tau and above 0, and, per bin of p, the share of cells the simulator
returned.

    .venv/bin/python bench/plus_calibration.py --model apcg_core/models/default [--model DIR ...] \
        [--per-type 40] [--seed 777] [--json bench/results/plus_calibration.json]
"""

from __future__ import annotations

import argparse

import numpy as np

from apcg_core.depth import DEFAULT_LIDAR
from apcg_core.families import apcg_plus as P
from apcg_core.families import load_model
from training import recognize as R

TYPES = ("A320neo", "737-800", "G550", "G650ER", "777-300ER")
OUTER_U = 0.6
BINS = (0.0, 0.1, 0.3, 0.5, 0.73, 0.9, 1.0)


def exact_keys(table, types) -> np.ndarray:
    """One key (sample, w, h) per cell the exact simulator returned."""
    from apcg_core.catalog import default_catalog
    from dataset_builder.simulate import Simulator
    cat = default_catalog()
    codes = table[:, 0].astype(np.int64)
    keys = []
    with Simulator("embree", DEFAULT_LIDAR, quantize=True, supersample=1) as sim:
        for code in np.unique(codes):
            sel = np.flatnonzero(codes == code)
            for i, c in zip(sel, sim.simulate_type(cat, types[code], table[sel]).clouds(),
                            strict=True):
                keys.append(cell_key(np.full(len(c.cell_w), i), c.cell_w, c.cell_h))
    return np.concatenate(keys)


def cell_key(sample, w, h) -> np.ndarray:
    return ((np.asarray(sample, np.int64) << 40) + ((np.asarray(w, np.int64) + (1 << 19)) << 20)
            + (np.asarray(h, np.int64) + (1 << 19)))


def reliability(model_dir: str, table: np.ndarray, types: list, returned: np.ndarray) -> dict:
    m = load_model(model_dir)
    conds = m.conditions([types[int(c)] for c in table[:, 0]], table[:, 1:]).table
    codes = conds[:, 0].astype(np.int64)
    r0, b0, rad = conds[:, 1], conds[:, 2], m.radius[codes]
    sample, w, h = P.box_cells(r0, b0, rad, m.lidar)
    u, v = P.sheet_coords(w, h, r0[sample], b0[sample], rad[sample], m.lidar)
    logit = P.sample_sheets(m.sheets(conds), sample, u, v)[:, 0].astype(np.float64)
    hit = np.isin(cell_key(sample, w, h), returned)
    p = 1.0 / (1.0 + np.exp(-logit))
    out = {"model": model_dir, "tau": m.tau, "cells_returned": int(len(returned)),
           "cells_returned_in_box": int(hit.sum())}
    outer = np.abs(u) > OUTER_U
    for name, k in (("all", np.ones(len(u), bool)), ("outer", outer), ("inner", ~outer)):
        rows = []
        for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
            q = k & (p >= lo) & ((p < hi) if hi < 1.0 else (p <= hi))
            rows.append({"p": [lo, hi], "cells": int(q.sum()),
                         "mean_p": round(float(p[q].mean()), 3) if q.any() else None,
                         "returned": round(float(hit[q].mean()), 3) if q.any() else None})
        out[name] = {"returned": int(hit[k].sum()), "sum_p": round(float(p[k].sum()), 1),
                     "above_tau": int((logit[k] > m.tau).sum()),
                     "above_0": int((logit[k] > 0).sum()), "bins": rows}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", action="append", required=True, help="APCG+ model directory")
    ap.add_argument("--per-type", type=int, default=40)
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument("--json")
    a = ap.parse_args()
    from bench_output import emit
    types = list(R.DEFAULT_TYPES)
    table = R.conditions(types, a.per_type, a.seed)
    keep = np.isin(np.asarray(types)[table[:, 0].astype(int)], TYPES) & (table[:, 1] > 1000.0)
    table = table[keep]
    returned = exact_keys(table, types)
    result = {"types": list(TYPES), "per_type": a.per_type, "seed": a.seed,
              "conditions": int(len(table)), "outer_u": OUTER_U,
              "models": [reliability(d, table, types, returned) for d in a.model]}
    for r in result["models"]:
        print(f"{r['model']} (tau {r['tau']}): {r['cells_returned']} exact returns")
        for g in ("all", "outer", "inner"):
            s = r[g]
            print(f"  {g}: returned {s['returned']}, sum p {s['sum_p']:.0f}, above tau "
                  f"{s['above_tau']}, above 0 {s['above_0']}; p -> returned: " + ", ".join(
                      f"{b['mean_p']}->{b['returned']}" for b in s["bins"] if b["cells"]))
    emit(result, a.json, show=False)


if __name__ == "__main__":
    main()
