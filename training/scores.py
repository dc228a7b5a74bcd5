"""Scoring one generated cloud against its standard cloud, and a band's summary of such pairs:
the metrics of the evaluation protocol (:mod:`training.protocol`, which draws the pairs and
writes the report) and of the faithfulness check (:mod:`training.faithfulness`), SPEC section 9.
"""

from __future__ import annotations

import numpy as np

from apcg_core.metrics import jsd, mmd
from apcg_core.pointflow import chamfer_distance

# JSD bins per axis, chosen by measurement (`evaluate.jsd_bins_study`: c = 6 separates a cloud's
# cell-jittered copy from the same copy 5 m off best in every band; at the literature's 28 even
# the jittered copy scores 0.42-0.98).
JSD_BINS = 6
MAX_POINTS = 2048
MIN_POINTS = 8
BANDS_M = {"aircraft": (3000, 6000, 9000, 12000, 15000, 18000.001),
           "drone": (100, 225, 350, 475, 600.001)}


def band_of(range_m: float, near: bool) -> str:
    """The slant-range band of a condition ("aircraft 3-6 km", "drone 100-225 m")."""
    edges = BANDS_M["drone" if near else "aircraft"]
    i = int(np.searchsorted(edges, range_m, side="right")) - 1
    i = min(max(i, 0), len(edges) - 2)
    unit, scale = ("m", 1) if near else ("km", 1e-3)
    lo, hi = edges[i] * scale, round(edges[i + 1] * scale)
    return f"{'drone' if near else 'aircraft'} {lo:g}-{hi:g} {unit}"


def band_order(name: str) -> tuple:
    kind, span, _unit = name.split(" ")
    return (kind != "aircraft", float(span.split("-")[0]))


def band_mean(bands: dict, key: str) -> float | None:
    """Mean of one score over the bands that have it (None where no band does)."""
    vals = [b[key] for b in bands.values() if b.get(key) is not None]
    return float(np.mean(vals)) if vals else None


def score_pair(std: np.ndarray, gen: np.ndarray, seed: int) -> dict:
    return {"mmd": mmd(std, gen, max_points=MAX_POINTS, seed=seed),
            "jsd": jsd(std, gen, bins=JSD_BINS, max_points=MAX_POINTS, seed=seed),
            "chamfer_m2": chamfer_distance(std, gen, max_points=MAX_POINTS, seed=seed),
            "n_standard": len(std), "n_generated": len(gen)}


def _mean(vals) -> float | None:
    vals = [v for v in vals if v is not None]
    return float(np.mean(vals)) if vals else None


def summarise(rows: list[dict]) -> dict:
    """A band's scores from its pairs' rows (low-point pairs counted, not averaged)."""
    ok = [r for r in rows if min(r["n_standard"], r["n_generated"]) >= MIN_POINTS]
    ratio = [r["n_generated"] / r["n_standard"] for r in rows if r["n_standard"] > 0]
    pct = (np.percentile(ratio, [10, 50, 90]).round(4).tolist() if ratio
           else [None, None, None])
    return {"pairs": len(rows), "scored": len(ok),
            "no_score": sum(r["n_generated"] == 0 or r["n_standard"] == 0 for r in rows),
            "low_points": sum(0 < min(r["n_standard"], r["n_generated"]) < MIN_POINTS
                              for r in rows),
            "mmd": _mean(r["mmd"] for r in ok), "jsd": _mean(r["jsd"] for r in ok),
            "chamfer_m2": _mean(r["chamfer_m2"] for r in ok),
            "points_standard": float(np.mean([r["n_standard"] for r in rows])),
            "points_generated": float(np.mean([r["n_generated"] for r in rows])),
            "points_ratio_p10_p50_p90": pct}
