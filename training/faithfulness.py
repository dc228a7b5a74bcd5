"""Faithfulness: does a generated cloud follow its own condition, or just look like a cloud?

For each scored pair (held-out sample i, condition [type, r0, beta0, pitch, yaw, roll]) the
exact embree simulator (the dataset's lidar, its ``quantize`` and ``supersample`` settings, the
type's catalog mesh found by name) makes two **decoy** standard clouds:

* (a) **yaw**: the same type and condition with the yaw moved :data:`YAW_SHIFT_DEG` toward the
  centre of the yaw range (yaw - 45 deg when yaw >= 0, else yaw + 45 deg);
* (b) **other type**: the same condition for a built-in catalog type of *another category*
  (``AircraftType.category``) in the same range band (``range_band``: far / near), drawn
  uniformly from those, in catalog order, by ``numpy.random.default_rng(pair seed)``; its name
  is recorded.

With MMD as the protocol computes it (``apcg_core.metrics.mmd``, clouds subsampled to
``scores.MAX_POINTS``, the pair's seed, the reference cloud first), the pair is **faithful**
when MMD(own standard, gen) < MMD(decoy a, gen) **and** MMD(own standard, gen) < MMD(decoy b,
gen). An empty decoy has no MMD and cannot be closer (that comparison passes). A pair whose own
standard cloud has fewer than ``scores.MIN_POINTS`` points is not scorable: counted
(``standard_too_few``), not in the share. A generated cloud with fewer than ``MIN_POINTS``
points (empty included) is **not faithful**, and counted (``too_few_points``). Per band:
share = faithful / scorable pairs, and the shares of pairs closer than decoy (a) alone
(``share_vs_yaw``) and decoy (b) alone (``share_vs_other_type``).

References on the same pairs (:data:`REFERENCES`): the paper's point z-buffer (backend
``points``) and embree with 2 x 2 rays per cell, scored as a model is. Everything is simulated
afresh per call (decoys batched per type), nothing is kept between calls.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from apcg_core.catalog import default_catalog
from apcg_core.errors import InputError
from apcg_core.metrics import mmd

from .data import DepthDataset
from .scores import MAX_POINTS, MIN_POINTS, band_mean, band_order, score_pair
from .scores import summarise as summarise_band

YAW_SHIFT_DEG = 45.0
# name: (backend, rays per cell side)
REFERENCES = {"points": ("points", 1), "embree 2x2": ("embree", 2)}


def _catalog_type(cat, ds: DepthDataset, name: str):
    try:
        return cat.get(name)
    except InputError:
        raise InputError(f"dataset {ds.directory} holds type {name!r}, which the catalog does "
                         "not know; the faithfulness score simulates decoys from catalog "
                         "meshes (add the type with `apcg catalog add`, or run without "
                         "faithfulness)") from None


def simulator(ds: DepthDataset, backend: str = "embree", supersample: int | None = None):
    """A simulator with the dataset's lidar and range quantization (and its rays per cell
    unless ``supersample`` is given)."""
    from dataset_builder.simulate import Simulator
    cfg = ds.header.get("config", {})
    k = int(cfg.get("supersample", 1)) if supersample is None else int(supersample)
    return Simulator(backend, ds.lidar, quantize=bool(cfg.get("quantize", True)),
                     supersample=k)


def _simulate(sim, cat, ds, names, table) -> list[np.ndarray]:
    """Clouds (n, 3) of rows ``table`` (N, 6) for the types ``names`` (N), batched per type."""
    out: list = [None] * len(table)
    names = np.asarray(names)
    for name in dict.fromkeys(names.tolist()):
        sel = np.flatnonzero(names == name)
        res = sim.simulate_type(cat, _catalog_type(cat, ds, name), table[sel])
        for k, c in zip(sel, res.clouds(), strict=True):
            out[k] = c.xyz
    return out


def simulated(backend: str, ds: DepthDataset, idx, supersample: int = 1):
    """Clouds of samples ``idx`` by one simulator backend, and the seconds per cloud (meshes and
    casters built before the clock starts)."""
    idx = np.asarray(idx)
    cat = default_catalog()
    table = ds.conditions[idx]
    names = [ds.types.name(int(c)) for c in table[:, 0]]
    with simulator(ds, backend, supersample) as sim:
        first = {n: k for k, n in reversed(list(enumerate(names)))}
        _simulate(sim, cat, ds, list(first), table[list(first.values())])  # warm up
        t0 = time.perf_counter()
        out = _simulate(sim, cat, ds, names, table)
        dt = time.perf_counter() - t0
    return out, dt / max(1, len(idx))


def yaw_shifted(table) -> np.ndarray:
    """Condition rows with the yaw moved :data:`YAW_SHIFT_DEG` toward the centre of its range."""
    out = np.array(table, dtype=np.float64, copy=True)
    d = np.radians(YAW_SHIFT_DEG)
    out[:, 4] = np.where(out[:, 4] >= 0, out[:, 4] - d, out[:, 4] + d)
    return out


def decoy_type(name: str, seed: int, cat=None) -> str:
    """The other-category, same-band built-in type that decoy (b) of a pair of type ``name`` and
    seed ``seed`` uses."""
    cat = default_catalog() if cat is None else cat
    own = cat.get(name)
    pool = [t.name for t in cat if t.source == "builtin" and t.range_band == own.range_band
            and t.category != own.category]
    if not pool:
        raise InputError(f"the catalog has no {own.range_band}-band type of a category other "
                         f"than {own.category!r} (type {name!r}) to use as a decoy")
    return pool[int(np.random.default_rng(seed).integers(len(pool)))]


@dataclass
class Decoys:
    """The two decoy clouds of every pair, the decoy types' names, how long they took."""

    yaw: list
    other: list
    other_type: list
    seconds: float


def decoys(ds: DepthDataset, idx, seeds) -> Decoys:
    """Decoys (a) and (b) of samples ``idx`` (pair seeds ``seeds``), simulated by embree."""
    t0 = time.perf_counter()
    idx = np.asarray(idx)
    cat = default_catalog()
    table = ds.conditions[idx]
    names = [_catalog_type(cat, ds, ds.types.name(int(c))).name for c in table[:, 0]]
    other = [decoy_type(n, int(s), cat) for n, s in zip(names, seeds, strict=True)]
    with simulator(ds) as sim:
        yaw = _simulate(sim, cat, ds, names, yaw_shifted(table))
        oth = _simulate(sim, cat, ds, other, table)
    return Decoys(yaw, oth, other, time.perf_counter() - t0)


def judge(std, gen, yaw, other, seed: int, mmd_own: float | None = None) -> dict:
    """One pair's verdict (module docstring). ``mmd_own`` saves recomputing MMD(std, gen)."""
    row = {"faithful": None, "closer_than_yaw": None, "closer_than_other_type": None,
           "mmd_yaw": None, "mmd_other_type": None, "n_decoy_yaw": len(yaw),
           "n_decoy_other_type": len(other)}
    if len(std) < MIN_POINTS:
        return {**row, "status": "standard_too_few"}
    if len(gen) < MIN_POINTS:
        return {**row, "faithful": False, "closer_than_yaw": False,
                "closer_than_other_type": False, "status": "too_few_points"}
    own = mmd(std, gen, max_points=MAX_POINTS, seed=seed) if mmd_own is None else mmd_own
    m_yaw = mmd(yaw, gen, max_points=MAX_POINTS, seed=seed)  # None when the decoy is empty
    m_oth = mmd(other, gen, max_points=MAX_POINTS, seed=seed)
    a = m_yaw is None or own < m_yaw
    b = m_oth is None or own < m_oth
    return {**row, "faithful": bool(a and b), "closer_than_yaw": bool(a),
            "closer_than_other_type": bool(b), "mmd_yaw": m_yaw, "mmd_other_type": m_oth,
            "status": "scored"}


def summarise(rows: list[dict]) -> dict:
    """A band's faithfulness from its pairs' :func:`judge` rows."""
    ok = [r for r in rows if r["status"] != "standard_too_few"]

    def share(key):
        return round(sum(bool(r[key]) for r in ok) / len(ok), 6) if ok else None
    return {"pairs": len(rows), "scorable": len(ok), "faithful": sum(bool(r["faithful"])
                                                                      for r in ok),
            "share": share("faithful"), "share_vs_yaw": share("closer_than_yaw"),
            "share_vs_other_type": share("closer_than_other_type"),
            "too_few_points": sum(r["status"] == "too_few_points" for r in rows),
            "standard_too_few": len(rows) - len(ok)}


def mean_shares(bands: dict) -> dict:
    """Mean over bands (each band alike) of the faithful share: all bands, aircraft, drones."""
    out = {}
    for key, pre in (("all", ""), ("aircraft", "aircraft"), ("drone", "drone")):
        vals = [b["faithfulness"]["share"] for n, b in bands.items()
                if n.startswith(pre) and b["faithfulness"]["share"] is not None]
        out[key] = float(np.mean(vals)) if vals else None
    return out


@dataclass
class Prepared:
    """What faithfulness needs of a set of pairs whatever the model: the standard clouds, the
    decoys, and the reference methods' reports. Made by :func:`prepare` for one call of
    ``protocol.score`` or one comparison (so it never outlives its pairs)."""

    pairs: object
    standards: list
    decoys: Decoys
    references: dict
    seconds: float

    def verdicts(self, gen, mmd_own=None) -> list[dict]:
        seeds = self.pairs.seed + np.arange(len(self.pairs))
        own = mmd_own if mmd_own is not None else [None] * len(gen)
        d = self.decoys
        return [{**judge(s, g, y, o, int(k), m), "decoy_type": t}
                for s, g, y, o, k, m, t in zip(self.standards, gen, d.yaw, d.other, seeds, own,
                                               d.other_type, strict=True)]

    def check(self, pairs) -> None:
        if pairs is not self.pairs and not (
                str(pairs.ds.directory) == str(self.pairs.ds.directory)
                and np.array_equal(pairs.idx, self.pairs.idx) and pairs.seed == self.pairs.seed):
            raise InputError("faithfulness was prepared for other pairs than these")


def band_report(pairs, rows: list[dict], verdicts: list[dict]) -> dict:
    """Per band: the protocol's summary of ``rows`` with the faithfulness of ``verdicts``."""
    bands = np.array(pairs.bands)
    out = {}
    for name in sorted(set(pairs.bands), key=band_order):
        sel = np.flatnonzero(bands == name)
        out[name] = {**summarise_band([rows[k] for k in sel]),
                     "faithfulness": summarise([verdicts[k] for k in sel])}
    return out


def prepare(pairs, standards=None) -> Prepared:
    """Decoys of ``pairs`` and the reference methods scored on them (MMD / JSD / points ratio
    per band by the protocol, and faithfulness)."""
    t0 = time.perf_counter()
    ds = pairs.ds
    stds = standards if standards is not None else [ds.standard_cloud(int(i))
                                                    for i in pairs.idx]
    dec = decoys(ds, pairs.idx, pairs.seed + np.arange(len(pairs)))
    prep = Prepared(pairs, stds, dec, {}, 0.0)
    for ref, (backend, k) in REFERENCES.items():
        clouds, sec = simulated(backend, ds, pairs.idx, k)
        rows = [score_pair(s, c, pairs.seed + j)
                for j, (s, c) in enumerate(zip(stds, clouds, strict=True))]
        verdicts = prep.verdicts(clouds, [r["mmd"] for r in rows])
        bands = band_report(pairs, rows, verdicts)
        prep.references[ref] = {
            "backend": backend, "supersample": k, "ms_per_cloud": round(1e3 * sec, 3),
            "bands": bands, "mean": {"mmd": band_mean(bands, "mmd"),
                                     "jsd": band_mean(bands, "jsd"),
                                     "faithfulness": mean_shares(bands)}}
    prep.seconds = time.perf_counter() - t0
    return prep


__all__ = ["REFERENCES", "YAW_SHIFT_DEG", "Decoys", "Prepared", "band_report", "decoy_type",
           "decoys", "judge", "mean_shares", "prepare", "simulated", "simulator", "summarise",
           "yaw_shifted"]
