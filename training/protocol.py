"""The evaluation protocol: the one way every command, figure and bench scores a model.

* **Pairs.** The dataset's held-out (test) split is cut once, by sample id, into two halves
  that never change: ``validation`` (where choices such as the Im2PC threshold tau are made)
  and ``test`` (where scores are reported). Pairs are drawn from one half, stratified by
  slant-range band (each band in proportion to its share, at least one), seeded; their number,
  per band, is reported.
* **Generation.** One generated cloud per pair, at the pair's condition (mapped into the
  model's types by name), noise seeded by ``seed`` per chunk of :data:`CHUNK` pairs.
* **Metrics** (SPEC section 9): MMD, JSD over :data:`JSD_BINS`^3 bins and Chamfer, each cloud
  subsampled (seeded) to at most :data:`MAX_POINTS`; a pair with fewer than :data:`MIN_POINTS`
  points on a side is counted (``low_points``; ``no_score`` when a side is empty) and not
  averaged. Point counts: the generated / standard ratio per pair (median, 10th, 90th
  percentile per band).
* **Floor.** Per band, up to :data:`FLOOR_PER_BAND` standard clouds against their own copy
  jittered inside each resolution cell: the best a generator can score.
* **Faithfulness** (when asked; :mod:`training.faithfulness`): per band, the share of pairs whose
  generated cloud is closer (MMD) to its own standard cloud than to the same type at yaw
  +-45 deg and to a type of another category, beside the same scores of two simulator
  references (the point z-buffer and embree 2 x 2) on the same pairs.

A report records the dataset, model, half, pairs per band, seed and every constant above, so
that the same call reproduces it to the digit.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np

from apcg_core.errors import InputError, check_int
from apcg_core.pointflow import pointflow_scores
from apcg_core.postprocess import cell_jitter

from .data import DepthDataset
from .scores import (  # noqa: F401 - the protocol's constants and pair scores, by their names here
    BANDS_M,
    JSD_BINS,
    MAX_POINTS,
    MIN_POINTS,
    band_mean,
    band_of,
    band_order,
    score_pair,
    summarise,
)

FLOOR_PER_BAND = 200
POINTFLOW_PER_BAND = 64
DEFAULT_PAIRS = 2000
CHUNK = 512  # pairs generated at a time (bounds memory)
HALVES = ("validation", "test")
WHOLE = "held-out"  # both halves: only where nothing is chosen on validation (apcg teach)
_HALF_SEED = 20251118  # fixes which held-out samples are validation; never change it


def half_mask(ds: DepthDataset, half: str) -> np.ndarray:
    """Which held-out samples belong to ``half`` ('validation' or 'test'): a fixed function of
    the sample id, so both halves are the same for every model, seed and command."""
    if half == WHOLE:
        return np.ones(len(ds), bool)
    if half not in HALVES:
        raise InputError(f"half must be one of {', '.join((*HALVES, WHOLE))}, got {half!r}")
    draw = np.random.default_rng(_HALF_SEED).random(int(ds.sample_id.max()) + 1)
    in_validation = draw[ds.sample_id] < 0.5
    return in_validation if half == "validation" else ~in_validation


@dataclass
class Pairs:
    """Held-out samples drawn for scoring: dataset indices, their bands, how they were drawn."""

    ds: DepthDataset
    idx: np.ndarray
    bands: list
    half: str
    seed: int
    asked: int | None

    def __len__(self) -> int:
        return len(self.idx)

    def record(self) -> dict:
        names, counts = np.unique(self.bands, return_counts=True)
        return {"dataset": str(self.ds.directory), "half": self.half, "seed": self.seed,
                "pairs_asked": self.asked, "pairs": len(self.idx),
                "pairs_per_band": {str(n): int(c) for n, c in zip(names, counts, strict=True)}}


def draw_pairs(data, n_pairs: int | None = DEFAULT_PAIRS, seed: int = 0,
               half: str = "test") -> Pairs:
    """A seeded subset of one half of the held-out split, stratified by band (all of the half
    when ``n_pairs`` is None or larger)."""
    ds = data if isinstance(data, DepthDataset) else DepthDataset(data, "test")
    if n_pairs is not None:
        check_int("pairs", n_pairs, 1)
    check_int("seed", seed, 0)
    pool = np.flatnonzero(half_mask(ds, half))
    if len(pool) == 0:
        raise InputError(f"dataset {ds.directory} has no held-out samples in its {half} half")
    near = ds.is_near(pool)
    bands = np.array([band_of(r, bool(n)) for r, n in zip(ds.conditions[pool, 1], near,
                                                           strict=True)])
    if n_pairs is None or n_pairs >= len(pool):
        picked = pool
    else:
        rng = np.random.default_rng(seed)
        names, counts = np.unique(bands, return_counts=True)
        share = np.maximum(1, np.round(counts / counts.sum() * n_pairs).astype(int))
        picked = np.concatenate([rng.choice(pool[bands == b], min(k, c), replace=False)
                                 for b, k, c in zip(names, share, counts, strict=True)])
    picked = np.sort(picked)
    near = ds.is_near(picked)
    return Pairs(ds, picked, [band_of(r, bool(n)) for r, n in
                              zip(ds.conditions[picked, 1], near, strict=True)],
                 half, seed, n_pairs)


def check_model_covers(model, pairs: Pairs) -> None:
    """Refuse, before any work, a model whose condition space does not hold every pair's
    condition, naming the dataset, the sample and the model (the model's own check would say
    only "row i" of a chunk)."""
    if not (hasattr(model, "space") and hasattr(model, "types")):
        return  # a stand-in of the tests (a decoy, prepared clouds): no condition space
    ds = pairs.ds
    ids = ds.sample_id[pairs.idx]
    try:
        model.space.check(ds.condition_rows(pairs.idx).recoded(model.types),
                          where=lambda i, j: f"dataset {ds.directory}, sample {ids[i]}")
    except InputError as exc:
        raise InputError(f"{exc}: the model {model.directory} is not made for this "
                         "dataset's conditions (its condition space: model.json)") from None


def generate(model, pairs: Pairs) -> tuple[list[np.ndarray], float]:
    """One generated cloud (n, 3) per pair, and the seconds generation took."""
    check_model_covers(model, pairs)
    t0 = time.perf_counter()
    out: list[np.ndarray] = []
    for s in range(0, len(pairs), CHUNK):
        cond = pairs.ds.condition_rows(pairs.idx[s:s + CHUNK])
        res = model.generate(cond, count=1, seed=pairs.seed + s)
        out += [c.xyz for c in res.cloud.split(len(cond))]
    return out, time.perf_counter() - t0


def jittered(ds: DepthDataset, i: int, seed: int) -> np.ndarray:
    """Sample ``i``'s standard cloud moved uniformly inside each of its cells (seeded): the floor's
    reference, as good as a generator can be."""
    return cell_jitter(ds.sample_cloud(i), ds.conditions[i, 2], ds.lidar, seed).xyz


def constants() -> dict:
    return {"jsd_bins": JSD_BINS, "max_points": MAX_POINTS, "min_points": MIN_POINTS,
            "floor_per_band": FLOOR_PER_BAND, "pointflow_per_band": POINTFLOW_PER_BAND,
            "chunk": CHUNK}


def score(model, pairs: Pairs, floor: bool = True, pointflow: bool = True,
          progress: bool = False, faithfulness=False) -> dict:
    """Scores of ``model`` on ``pairs``: per band, with the floor and the PointFlow set metrics
    when asked, and a row per pair. ``faithfulness``: True (or a
    :class:`training.faithfulness.Prepared` of these pairs, to share decoys and references
    between models) adds each band's faithfulness, the references and the mean shares."""
    t0 = time.perf_counter()
    gen, t_gen = generate(model, pairs)
    ds = pairs.ds
    rows, stds, floor_rows = [], [], []
    floor_count: dict = {}
    for j, i in enumerate(pairs.idx):
        std = ds.standard_cloud(int(i))
        stds.append(std)
        rows.append(score_pair(std, gen[j], pairs.seed + j))
        band = pairs.bands[j]
        if floor and floor_count.get(band, 0) < FLOOR_PER_BAND:
            floor_count[band] = floor_count.get(band, 0) + 1
            jit = jittered(ds, int(i), pairs.seed + j)
            floor_rows.append((band, score_pair(std, jit, pairs.seed + j)))
        if progress and (j + 1) % 500 == 0:
            print(f"scored {j + 1}/{len(pairs)} pairs", file=sys.stderr, flush=True)
    bands = np.array(pairs.bands)
    out_bands = {}
    for name in sorted(set(pairs.bands), key=band_order):
        sel = np.flatnonzero(bands == name)
        entry = summarise([rows[k] for k in sel])
        if floor:
            entry["floor"] = summarise([r for b, r in floor_rows if b == name])
        if pointflow:
            pf = sel[:POINTFLOW_PER_BAND]
            try:
                entry["pointflow"] = pointflow_scores([gen[k] for k in pf],
                                                      [stds[k] for k in pf], max_points=512,
                                                      seed=pairs.seed).to_dict()
            except InputError as exc:  # e.g. every generated cloud of the band empty
                entry["pointflow"] = {"error": str(exc)}
        out_bands[name] = entry
    names = ds.types.names
    extra: list = [{}] * len(pairs)
    seconds = {"generate": round(t_gen, 6)}
    if faithfulness:
        from . import faithfulness as fa
        t1 = time.perf_counter()
        prep = faithfulness if isinstance(faithfulness, fa.Prepared) else fa.prepare(pairs,
                                                                                      stds)
        prep.check(pairs)
        verdicts = prep.verdicts(gen, [r["mmd"] for r in rows])
        for name, entry in fa.band_report(pairs, rows, verdicts).items():
            out_bands[name]["faithfulness"] = entry["faithfulness"]
        extra = [{k: v[k] for k in ("faithful", "closer_than_yaw", "closer_than_other_type",
                                    "decoy_type", "mmd_yaw", "mmd_other_type")}
                 for v in verdicts]
        seconds["faithfulness"] = round(time.perf_counter() - t1, 2)  # shared work excluded
    mean = {k: band_mean(out_bands, k) for k in ("mmd", "jsd")}
    report = {"protocol": constants(), **pairs.record(), "model": str(model.directory),
              "family": model.family, "tau": getattr(model, "tau", None), "bands": out_bands,
              "mean": mean,
              "per_pair": [{"sample_id": int(ds.sample_id[i]), "type": names[int(
                  ds.conditions[i, 0])], "band": pairs.bands[j],
                  "range_m": float(ds.conditions[i, 1]), **rows[j], **extra[j]}
                  for j, i in enumerate(pairs.idx)],
              "seconds": seconds}
    if faithfulness:
        mean["faithfulness"] = fa.mean_shares(out_bands)
        report["references"] = prep.references
    seconds["total"] = round(time.perf_counter() - t0, 2)
    return report


def per_type(report: dict) -> dict:
    """Mean MMD / JSD and pair counts per type name, from a report's pairs."""
    out: dict = {}
    for r in report["per_pair"]:
        out.setdefault(r["type"], []).append(r)
    return {name: {k: v for k, v in summarise(rows).items()
                   if k in ("pairs", "scored", "mmd", "jsd", "points_standard",
                            "points_generated")}
            for name, rows in sorted(out.items())}


def untrained(model, out_dir, seed: int = 0):
    """The same network as ``model``, freshly initialised, from its family."""
    from apcg_core.families import get_family
    return get_family(model.family, need="untrained").untrained(model, out_dir, seed)


def tau_key(tau: float) -> str:
    """A candidate threshold as a report's key: the shortest text that reads back as exactly
    ``tau`` ("0.5", "-0.99", "0.1234561"), so two candidates never share a key and the key is
    the value that was scored."""
    short = f"{tau:g}"
    return short if float(short) == tau else repr(float(tau))


def check_taus(model, taus) -> list[float]:
    """Every candidate threshold checked against the model's range (``check_tau``) before any
    is scored, duplicates (by exact value) dropped in order; an empty list is refused."""
    try:
        values = list(taus)
    except TypeError:
        raise InputError(f"taus must be a list of numbers, got {taus!r}") from None
    if not values:
        raise InputError("taus: no candidate thresholds given; give at least one (or leave "
                         "them out for the model's own)")
    checked = []
    for tau in values:
        try:
            v = model.check_tau(tau)
        except InputError as exc:
            raise InputError(f"--taus: {exc}; no threshold was scored") from exc
        if v not in checked:
            checked.append(v)
    return checked


def choose_tau(model, data, taus=None, n_pairs: int = 400, seed: int = 0) -> dict:
    """The model's output threshold tau (the cGAN's Im2PC threshold, APCG+'s hit logit: the
    model's ``TAUS`` are the candidates unless ``taus`` are given) with the lowest mean (over
    bands) MMD among those that leave at most 1% of the clouds empty, on the **validation**
    half only (same pairs and noise for every threshold). Every candidate is checked against
    the model's range before any is scored; ``best`` is exactly a scored candidate, and the
    sweep's keys (:func:`tau_key`) read back as the values scored."""
    if getattr(model, "tau", None) is None:
        raise InputError(f"{model.directory} is a {model.family} model, which has no output "
                         "threshold to choose")
    taus = check_taus(model, model.TAUS if taus is None else taus)
    pairs = draw_pairs(data, n_pairs, seed, half="validation")
    kept = model.tau
    rows, value = {}, {}
    try:
        for tau in taus:
            model.tau = tau
            rep = score(model, pairs, floor=False, pointflow=False)
            no_score = sum(b["no_score"] for b in rep["bands"].values())
            ratios = [b["points_ratio_p10_p50_p90"][1] for b in rep["bands"].values()
                      if b["points_ratio_p10_p50_p90"][1] is not None]
            key = tau_key(tau)
            value[key] = tau
            rows[key] = {
                "mmd": rep["mean"]["mmd"], "jsd": rep["mean"]["jsd"], "no_score": no_score,
                "points_ratio_median_mean_over_bands": float(np.mean(ratios)) if ratios else None}
    finally:
        model.tau = kept
    allowed = [k for k, r in rows.items() if r["no_score"] <= 0.01 * len(pairs)
               and r["mmd"] is not None]
    if not allowed:
        raise InputError(f"every threshold of {list(rows)} leaves more than 1% of the "
                         "validation clouds empty; the model generates (almost) nothing")
    best = min(allowed, key=lambda k: rows[k]["mmd"])
    return {**pairs.record(), "protocol": constants(), "model": str(model.directory),
            "taus": rows, "best": value[best]}


__all__ = ["BANDS_M", "DEFAULT_PAIRS", "JSD_BINS", "MAX_POINTS", "MIN_POINTS", "Pairs",
           "band_mean", "band_of", "band_order", "check_taus", "choose_tau", "draw_pairs",
           "generate", "half_mask", "per_type", "score", "score_pair", "summarise", "tau_key",
           "untrained"]
