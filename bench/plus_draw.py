"""How an APCG+ model's cells are drawn from its calibrated hit probabilities (issue 34,
criterion 2: faithfulness and MMD per band).

The model reads a hit logit per box cell (``PlusModel.box_reads``) and draws its returns from
them by its draw (``apcg_core/families/plus_draw.py``). Its probabilities are calibrated
(stop 45: the share of cells that are returns where the condition cannot tell), so a thin
wing seen edge-on reads p ~ 0.4-0.7 along a row of cells: thresholded, the whole row is
drawn, where the simulator's cell-centre rays meet the wing in a share of them. Draws scored:

* ``threshold``: the cells above tau (every model before stop 49);
* ``diffuse-rows``: the package's error diffusion along each box row (the shipped default
  since stop 49): a row keeps round(its running sum of p) cells after each cell;
* ``diffuse-2d`` (here only, not in the package): Floyd-Steinberg over each cloud's box
  (7/16 right, 3/16, 5/16, 1/16 to the next row), rows in h order.

The diffused draws count cells below logit tau + ``--span`` as p = 0 (default -6, p 0.0025,
the shipped default's; stop 48 measured -3 with the cells between counted); ``threshold``
reads the shipped reader's cells. Scored by the evaluation protocol
(``training.protocol.score`` with faithfulness, the decoys prepared once for every draw), tau
the model's:

    .venv/bin/python bench/plus_draw.py --model apcg_core/models/default --data data/cpu \\
        --draw threshold --draw diffuse-rows --json bench/results/plus_draw.json

(data/cpu: ``apcg dataset build --config cpu -o data/cpu``; 2,001 test-half pairs, as
``apcg evaluate``; about 6 minutes a draw on a 2-core machine.)
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.families.apcg_plus import PlusModel  # noqa: E402

DRAWS = ("threshold", "diffuse-rows", "diffuse-2d")


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
    """The model with its cells drawn by ``draw`` (module docstring): the package's draws
    through its own readers, ``diffuse-2d`` on the numpy reader's cells."""

    draw_2d = False
    span = -6.0

    def clouds_of(self, table, sheets, compiled=None):
        if not self.draw_2d:
            return super().clouds_of(table, sheets, compiled=compiled)
        sample, w, h, read = self.box_reads(table, sheets, self.tau + self.span)
        p = 1.0 / (1.0 + np.exp(-(read[:, 0].astype(np.float64) - self.tau)))
        p[read[:, 0] - self.tau <= self.span] = 0.0
        kept = diffuse_2d(sample, h, w, p, self._fs)
        return self.cloud_of_cells(table, sample[kept], w[kept], h[kept], read[kept, 1])

    @classmethod
    def with_draw(cls, directory, draw: str, span: float):
        from apcg_core.families.plus_draw import DRAWS, Draw
        m = cls(directory)
        if draw in DRAWS:
            m.draw = DRAWS[draw] if not DRAWS[draw].diffused else Draw(draw, span)
        else:
            m.draw_2d, m.span, m._fs = True, span, _floyd_steinberg_kernel()
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
    ap.add_argument("--span", type=float, default=-6.0)
    ap.add_argument("--json", help="write the per-band figures here")
    args = ap.parse_args(argv)
    ds = DepthDataset(args.data, "test")
    pairs = protocol.draw_pairs(ds, args.pairs, 0, "test")
    out = {"command": "bench/plus_draw.py " + shlex.join(sys.argv[1:]), "model": args.model,
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
