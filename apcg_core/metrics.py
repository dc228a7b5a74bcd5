"""The paper's point-cloud metrics (Appendix A; SPEC section 9): MMD and JSD, and set means.

Every function takes clouds as (N, 3) arrays in metres. Work is chunked so that two
20,000-point clouds fit in a few hundred MB; ``max_points`` subsamples (seeded) for large
evaluations. A pair with an empty cloud has no score: the pair functions return ``None``
and :func:`set_mean` counts it, so no NaN ever enters a mean.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError, check_int

CHUNK_ELEMENTS = 1 << 22  # distances computed at once (32 MB of float64)
JSD_BINS_DEFAULT = 28  # the point-cloud literature's habit; the evaluation chooses c by measurement
# Most bins a side: JSD's flat cell index (x c + y) c + z reaches c^3 - 1, which int64 holds up
# to c = 2^21 (c^3 = 2^63); past it the index wraps and cells of different points collide.
JSD_BINS_MAX = 2**21


def as_cloud(points, name: str = "cloud") -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.shape in ((0,), (0, 3)):  # no points ([] or an empty (N, 3) array)
        return p.reshape(0, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise InputError(f"{name} contains NaN or infinite coordinates")
    if len(p) and (big := float(np.abs(p).max())) > MAX_COORDINATE_M:
        # squared distances of coordinates past ~1e154 overflow to inf, and a NaN score
        # clipped to 0 read as a perfect one
        raise InputError(f"{name} has a coordinate of {big:.6g} m; accepted: coordinates "
                         f"within +-{MAX_COORDINATE_M:g} m")
    return p


MAX_COORDINATE_M = 1e12  # far past any lidar's range, and its squares far from overflow


def subsample(points, max_points: int | None, seed: int = 0) -> np.ndarray:
    """At most ``max_points`` points, drawn without replacement (seeded); small clouds as is."""
    p = as_cloud(points)
    check_int("seed", seed, 0)  # numpy refuses a negative seed, and None draws unseeded
    if max_points is not None:
        check_int("max_points", max_points, 1)
    if max_points is None or len(p) <= max_points:
        return p
    idx = np.random.default_rng(seed).choice(len(p), size=max_points, replace=False)
    return p[np.sort(idx)]


def _centred_pair(a, b, max_points, seed):
    a = subsample(as_cloud(a, "a"), max_points, seed)
    b = subsample(as_cloud(b, "b"), max_points, seed + 1)
    # Differences only matter; centring first keeps |a|^2 + |b|^2 - 2ab exact at 18 km.
    c = np.concatenate([a, b]).mean(axis=0) if len(a) + len(b) else np.zeros(3)
    return a - c, b - c


def _sq_dist_chunks(a: np.ndarray, b: np.ndarray, chunk: int = CHUNK_ELEMENTS):
    """Yield squared distances between rows of a and all of b, a block of rows at a time."""
    bb = (b * b).sum(axis=1)
    rows = max(1, chunk // max(1, len(b)))
    for i in range(0, len(a), rows):
        ai = a[i:i + rows]
        d2 = (ai * ai).sum(axis=1)[:, None] + bb[None, :] - 2.0 * ai @ b.T
        np.maximum(d2, 0.0, out=d2)
        yield d2


def _kth_smallest(a, b, k: int, chunk: int) -> float:
    """Exact k-th smallest (0-based) squared cross distance with bounded memory.

    Histogram refinement: each pass counts, by comparison, the values below the current
    interval and inside it, and histograms the inside; the next interval is the bin holding
    rank k widened by one bin each side (so float rounding in the bin index cannot lose it).
    When few values remain they are collected and partitioned exactly.
    """
    lo, hi = 0.0, max(float(d2.max()) for d2 in _sq_dist_chunks(a, b, chunk))
    nbins = 4096
    while True:
        below = inside = 0
        vmin, vmax = np.inf, -np.inf
        counts = np.zeros(nbins, dtype=np.int64)
        width = (hi - lo) / nbins
        for d2 in _sq_dist_chunks(a, b, chunk):
            below += int(np.count_nonzero(d2 < lo))
            sel = d2[(d2 >= lo) & (d2 <= hi)]
            inside += sel.size
            if sel.size:
                vmin, vmax = min(vmin, float(sel.min())), max(vmax, float(sel.max()))
                if width > 0:
                    idx = np.clip(((sel - lo) / width).astype(np.int64), 0, nbins - 1)
                    counts += np.bincount(idx, minlength=nbins)
        if not below <= k < below + inside:
            raise RuntimeError(f"median search lost rank {k} (below={below}, inside={inside})")
        if vmin == vmax:
            return vmin
        if inside <= chunk:
            vals = np.concatenate([d2[(d2 >= lo) & (d2 <= hi)].ravel()
                                   for d2 in _sq_dist_chunks(a, b, chunk)])
            return float(np.partition(vals, k - below)[k - below])
        j = int(np.searchsorted(below + np.cumsum(counts), k, side="right"))
        lo, hi = max(lo, lo + (j - 1) * width), min(hi, lo + (j + 2) * width)


def median_cross_distance(a, b, chunk: int = CHUNK_ELEMENTS) -> float:
    """Median of all n*m distances ||a_i - b_j|| (numpy's median: mean of the two middle values)."""
    n = len(a) * len(b)
    if n <= chunk:
        d2 = next(_sq_dist_chunks(a, b, n))
        return float(np.median(np.sqrt(d2)))
    hi_k = n // 2
    upper = np.sqrt(_kth_smallest(a, b, hi_k, chunk))
    if n % 2:
        return float(upper)
    return float(0.5 * (upper + np.sqrt(_kth_smallest(a, b, hi_k - 1, chunk))))


def _kernel_mean(x, y, sigma: float, chunk: int) -> float:
    total = 0.0
    if sigma > 0:
        g = -1.0 / (2.0 * sigma * sigma)
        for d2 in _sq_dist_chunks(x, y, chunk):
            total += float(np.exp(d2 * g).sum())
    else:  # the kernel's limit for sigma -> 0: 1 on coincident points, else 0
        for d2 in _sq_dist_chunks(x, y, chunk):
            total += float((d2 == 0.0).sum())
    return total / (len(x) * len(y))


def mmd(a, b, max_points: int | None = None, seed: int = 0,
        chunk: int = CHUNK_ELEMENTS) -> float | None:
    """Maximum mean discrepancy (paper eq. A1), Gaussian kernel, sigma = median cross distance.

    MMD = mean k(a, a') + mean k(b, b') - 2 mean k(a, b), all pairs including i = j (the
    biased estimator, a squared norm, hence >= 0: tiny negative rounding is clipped to 0).
    Returns None when either cloud is empty.
    """
    a, b = _centred_pair(a, b, max_points, seed)
    if len(a) == 0 or len(b) == 0:
        return None
    sigma = median_cross_distance(a, b, chunk)
    value = (_kernel_mean(a, a, sigma, chunk) + _kernel_mean(b, b, sigma, chunk)
             - 2.0 * _kernel_mean(a, b, sigma, chunk))
    return max(0.0, value)


def _kl2(p: np.ndarray, s: np.ndarray) -> float:
    nz = p > 0
    return float((p[nz] * np.log2(p[nz] / s[nz])).sum())


SPAN_EPS_M = 1e-6


def jsd(a, b, bins: int = JSD_BINS_DEFAULT, max_points: int | None = None,
        seed: int = 0) -> float | None:
    """Jensen-Shannon divergence of occupancy over a c^3 grid (paper eq. A2), log base 2.

    The grid is the axis-aligned box (observation axes) holding both clouds, ``bins`` cells
    per axis. 0 <= JSD <= 1. Returns None when either cloud is empty. On sparse clouds JSD
    saturates (SPEC section 9): always report it with its ``bins`` and the point counts.
    """
    check_int("bins", bins, 1)
    if bins > JSD_BINS_MAX:
        raise InputError(f"bins = {bins} is too many; accepted: 1 .. {JSD_BINS_MAX} (2^21: the "
                         "flat index of the c^3 cells must fit int64, c^3 <= 2^63)")
    a, b = _centred_pair(a, b, max_points, seed)
    if len(a) == 0 or len(b) == 0:
        return None
    both = np.concatenate([a, b])
    lo = both.min(axis=0)
    span = both.max(axis=0) - lo
    # an axis both clouds hardly span (a flat target seen edge-on) is one bin: cutting a
    # micrometre into c bins would sort points by float rounding (a copy scored JSD 1)
    span[span < SPAN_EPS_M] = 1.0
    cell = np.clip(((both - lo) / span * bins).astype(np.int64), 0, bins - 1)
    flat = (cell[:, 0] * bins + cell[:, 1]) * bins + cell[:, 2]
    keys, inv = np.unique(flat, return_inverse=True)
    p = np.bincount(inv[: len(a)], minlength=len(keys)) / len(a)
    q = np.bincount(inv[len(a):], minlength=len(keys)) / len(b)
    s = 0.5 * (p + q)
    return float(min(1.0, max(0.0, 0.5 * _kl2(p, s) + 0.5 * _kl2(q, s))))


@dataclass
class SetScore:
    """Mean of a metric over matched pairs, with the pairs that had no score counted."""

    metric: str
    mean: float | None  # None when no pair had a score
    n_pairs: int
    n_scored: int
    n_no_score: int  # pairs with an empty cloud
    params: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"metric": self.metric, "mean": self.mean, "n_pairs": self.n_pairs,
                "n_scored": self.n_scored, "n_no_score": self.n_no_score, **self.params}


def set_mean(metric: Callable[..., float | None], pairs: Iterable[tuple], name: str | None = None,
             **kwargs) -> SetScore:
    """Mean of ``metric(a, b, **kwargs)`` over pairs (a, b) of the same condition.

    Pairs whose score is None (an empty cloud) are counted in ``n_no_score``, never averaged.
    """
    scores = []
    n = 0
    for a, b in pairs:
        n += 1
        v = metric(a, b, **kwargs)
        if v is not None:
            scores.append(v)
    mean = float(np.mean(scores)) if scores else None
    return SetScore(name or getattr(metric, "__name__", "metric"), mean, n, len(scores),
                    n - len(scores), dict(kwargs))


def mmd_mean(pairs: Iterable[tuple], **kwargs) -> SetScore:
    """Set mean of MMD over matched pairs (the paper's MMD-bar)."""
    return set_mean(mmd, pairs, "mmd", **kwargs)


def jsd_mean(pairs: Iterable[tuple], bins: int = JSD_BINS_DEFAULT, **kwargs) -> SetScore:
    """Set mean of JSD over matched pairs (the paper's JSD-bar), with c recorded."""
    return set_mean(jsd, pairs, "jsd", bins=bins, **kwargs)
