"""How an APCG+ model's cells are drawn from its calibrated hit probabilities (issue 34,
criterion 2: faithfulness and MMD per band).

The model reads a hit logit per box cell (``PlusModel.box_reads``) and keeps the cells above
tau (``threshold``, the shipped rule). Its probabilities are calibrated (stop 45: the share of
cells that are returns where the condition cannot tell), so a thin wing seen edge-on reads
p ~ 0.4-0.7 along a row of cells: thresholded, the whole row is drawn, where the simulator's
cell-centre rays meet the wing in a share of them. The other draws keep that share:

* ``diffuse-rows``: error diffusion along each box row (w ascending): a cell is kept when its
  p plus the error carried from the cell before reaches 0.5, and the error (p + carried - kept)
  goes on to the next cell; every row starts at 0. Deterministic, and a row's kept count is
  its summed p, rounded;
* ``diffuse-2d``: Floyd-Steinberg over each cloud's box (7/16 right, 3/16, 5/16, 1/16 to the
  next row), rows in h order.

Candidate cells: those of rows with a sheet column above logit ``--span`` (default -3, p 0.047)
for the diffused draws, tau for ``threshold`` (the shipped reader's cells). Scored by the
evaluation protocol (``training.protocol.score`` with faithfulness), tau the model's:

    .venv/bin/python bench/plus_draw.py --model apcg_core/models/default --data data/cpu \\
        --draw threshold --draw diffuse-rows --json bench/results/plus_draw.json

(data/cpu: ``apcg dataset build --config cpu -o data/cpu``; 2,001 test-half pairs, as
``apcg evaluate``; about 6 minutes a draw on a 2-core machine.)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.families.apcg_plus import PlusModel  # noqa: E402

DRAWS = ("threshold", "diffuse-rows", "diffuse-2d")


def _rows_kernel():
    import numba

    @numba.njit(cache=True)
    def diffuse_rows(sample, h, p):
        kept = np.zeros(len(p), np.bool_)
        err = 0.0
        for i in range(len(p)):
            if i == 0 or sample[i] != sample[i - 1] or h[i] != h[i - 1]:
                err = 0.0
            v = p[i] + err
            kept[i] = v >= 0.5
            err = v - (1.0 if kept[i] else 0.0)
        return kept
    return diffuse_rows


def _floyd_steinberg_kernel():
    import numba

    @numba.njit(cache=True)
    def floyd_steinberg(g):
        g = g.copy()
        rows, cols = g.shape
        out = np.zeros((rows, cols), np.bool_)
        for y in range(rows):
            for x in range(cols):
                v = g[y, x]
                out[y, x] = v >= 0.5
                e = v - (1.0 if out[y, x] else 0.0)
                if x + 1 < cols:
                    g[y, x + 1] += e * 7 / 16
                if y + 1 < rows:
                    if x > 0:
                        g[y + 1, x - 1] += e * 3 / 16
                    g[y + 1, x] += e * 5 / 16
                    if x + 1 < cols:
                        g[y + 1, x + 1] += e * 1 / 16
        return out
    return floyd_steinberg


def diffuse_2d(sample, h, w, p, kernel):
    kept = np.zeros(len(p), bool)
    for s in np.unique(sample):
        idx = np.flatnonzero(sample == s)
        hh, ww = h[idx] - h[idx].min() + 1, w[idx] - w[idx].min() + 1
        g = np.zeros((hh.max() + 2, ww.max() + 2))
        g[hh, ww] = p[idx]
        kept[idx] = kernel(g)[hh, ww]
    return kept


class DrawnModel(PlusModel):
    """The model with its cells drawn by ``draw`` (module docstring), the numpy reader's."""

    draw = "threshold"
    span = -3.0

    def clouds_of(self, table, sheets, compiled=None):
        if self.draw == "threshold":
            return super().clouds_of(table, sheets, compiled=False)
        sample, w, h, read = self.box_reads(table, sheets, min(self.span, self.tau))
        p = 1.0 / (1.0 + np.exp(-(read[:, 0].astype(np.float64) - self.tau)))
        if self.draw == "diffuse-rows":
            kept = self._rows(sample, h, p)
        else:
            kept = diffuse_2d(sample, h, w, p, self._fs)
        return self.cloud_of_cells(table, sample[kept], w[kept], h[kept], read[kept, 1])

    @classmethod
    def with_draw(cls, directory, draw: str, span: float):
        m = cls(directory)
        m.draw, m.span = draw, span
        m._rows, m._fs = _rows_kernel(), _floyd_steinberg_kernel()
        return m


def main(argv=None) -> int:
    from bench_output import emit

    from training import protocol
    from training.evaluate import DepthDataset
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="apcg_core/models/default")
    ap.add_argument("--data", default="data/cpu")
    ap.add_argument("--draw", action="append", choices=DRAWS, help="repeatable")
    ap.add_argument("--pairs", type=int, default=2000, help="as apcg evaluate (2,001 pairs)")
    ap.add_argument("--span", type=float, default=-3.0)
    ap.add_argument("--json", help="write the per-band figures here")
    args = ap.parse_args(argv)
    ds = DepthDataset(args.data, "test")
    pairs = protocol.draw_pairs(ds, args.pairs, 0, "test")
    out = {"command": "bench/plus_draw.py " + " ".join(sys.argv[1:]), "model": args.model,
           "pairs": len(pairs), "span": args.span, "draws": {}}
    prep = None
    for draw in args.draw or ["threshold", "diffuse-rows"]:
        model = DrawnModel.with_draw(args.model, draw, args.span)
        t0 = time.perf_counter()
        if prep is None:  # decoys and references once, shared by every draw
            from training import faithfulness as fa
            stds = [ds.standard_cloud(int(i)) for i in pairs.idx]
            prep = fa.prepare(pairs, stds)
        rep = protocol.score(model, pairs, floor=False, pointflow=False, faithfulness=prep)
        bands = {b: {"mmd": e["mmd"], "jsd": e["jsd"],
                     "faithful": e["faithfulness"]["faithful"],
                     "scorable": e["faithfulness"]["scorable"],
                     "points_ratio_p10_p50_p90": e.get("points_ratio_p10_p50_p90")}
                 for b, e in rep["bands"].items()}
        out["draws"][draw] = {"bands": bands, "mean": rep["mean"],
                              "seconds": round(time.perf_counter() - t0, 1)}
        print(f"{draw} ({out['draws'][draw]['seconds']} s): mean {rep['mean']}")
        for b, e in bands.items():
            print(f"  {b:18s} MMD {e['mmd']:.6f}  JSD {e['jsd']:.4f}  faithful "
                  f"{e['faithful']}/{e['scorable']}")
    emit(out, args.json, show=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
