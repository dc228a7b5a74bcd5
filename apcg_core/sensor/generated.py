"""The photon stage on a generated (or any one-point-per-cell) cloud (SPEC section 8).

A generator draws the standard cloud: one range per cell, no sub-rays and no surface normals.
Each point becomes one return filling its cell (K = 1), and its incidence is read off the
cloud itself: the range's slope across neighbouring cells (centred differences where both
neighbours exist, one-sided at an edge, flat with none) gives the surface normal, and
cos = 1 / sqrt(1 + (dr/dx)^2 + (dr/dy)^2) with dx, dy the cell's width and height at that
range. Partial cells (a wing edge across a cell) cannot be told apart and count as full.

A family that draws at any lidar's cells (``ANY_LIDAR``: APCG+ reads its sheet at them) gives
sub-rays instead (issue 33): it draws the same conditions at the K-times finer lidar
(K = :data:`SUB_READS`, odd, so that the finer cells' centres are exactly the K x K centred
sub-ray grid of SPEC section 4), unquantized; each finer point is one sub-ray of its cell with
its own range, and its incidence from the slope across finer cells. Partial cells then count as
partial, and a cell's ranges keep their spread, as the simulator's sub-rays do. The slope is
taken over a baseline of :data:`SLOPE_BASELINE` of the family's own resolution where it says
one (``drawn_resolution_m``: APCG+ draws on a sheet of 2R / S metres a pixel), not over one
lidar cell: below its resolution a generator's ranges are its interpolation, and their slopes
there are the interpolation's (near a 777-300ER at 3-6 km a cell is a tenth of a sheet pixel).
"""

from __future__ import annotations

import numpy as np

from ..cloud import PointCloud
from ..lidar import LidarParams
from .stage import SubRayHits


def _neighbour_range(key: np.ndarray, sorted_keys: np.ndarray, ranges: np.ndarray,
                     offset: int) -> np.ndarray:
    """The range at key + offset, NaN where that cell has no point."""
    want = key + offset
    at = np.minimum(np.searchsorted(sorted_keys, want), len(sorted_keys) - 1)
    found = sorted_keys[at] == want
    return np.where(found, ranges[at], np.nan)


def _slope(r: np.ndarray, minus: np.ndarray, plus: np.ndarray) -> np.ndarray:
    both = np.isfinite(minus) & np.isfinite(plus)
    out = np.zeros(len(r))
    out[both] = (plus[both] - minus[both]) / 2.0
    only_p = np.isfinite(plus) & ~both
    out[only_p] = plus[only_p] - r[only_p]
    only_m = np.isfinite(minus) & ~both
    out[only_m] = r[only_m] - minus[only_m]
    return out


def _strides(stride, n_samples: int) -> np.ndarray:
    k = np.broadcast_to(np.asarray(stride, np.int64), (n_samples,))
    if n_samples and k.min() < 1:
        raise ValueError(f"slope strides must be >= 1 cell, got {int(k.min())}")
    return k


def hits_of_cloud(cloud: PointCloud, elevation: np.ndarray, lidar: LidarParams,
                  n_samples: int, stride=1, stride_h=None) -> SubRayHits:
    """One return per point of ``cloud`` (``cloud.sample`` in 0..n_samples-1, ``elevation``
    per sample for the cell heights), its incidence from the range slope between the cells
    ``stride`` cells away on either side across the row (``stride_h`` up and down the column;
    default the same): one number, or one per sample."""
    s = (np.zeros(len(cloud), np.int64) if cloud.sample is None
         else np.asarray(cloud.sample, np.int64))
    w = cloud.cell_w.astype(np.int64)
    h = cloud.cell_h.astype(np.int64)
    r = cloud.range_m.astype(np.float64)
    k_w = _strides(stride, n_samples)
    k_h = k_w if stride_h is None else _strides(stride_h, n_samples)
    pad = int(max(k_w.max(), k_h.max())) if n_samples else 1
    span = lidar.width + 2 * pad  # a row of keys with room for the neighbours of the edge cells
    key = (s * (lidar.height + 2 * pad) + (h - lidar.h_min + pad)) * span + (w - lidar.w_min + pad)
    order = np.argsort(key, kind="stable")
    key, s, w, h, r = key[order], s[order], w[order], h[order], r[order]
    kw, kh = k_w[s], k_h[s]
    dr_w = _slope(r, _neighbour_range(key, key, r, -kw), _neighbour_range(key, key, r, kw)) / kw
    dr_h = _slope(r, _neighbour_range(key, key, r, -kh * span),
                  _neighbour_range(key, key, r, kh * span)) / kh
    beta = np.asarray(elevation, np.float64)[s] + h * lidar.r_beta
    dx = r * lidar.r_alpha * np.cos(beta)
    dy = r * lidar.r_beta
    cos = 1.0 / np.sqrt(1.0 + (dr_w / dx) ** 2 + (dr_h / dy) ** 2)
    # key order is sample, then row, then column: grouped by sample as the stage wants
    return SubRayHits(s, w.astype(np.int32), h.astype(np.int32), r, cos, n_samples, 1)


# Sub-reads per cell side for a family that draws at any lidar: odd (the finer cells' centres
# are then the centred sub-ray grid), and 3 x 3 = 9 sub-rays a cell, near the simulator's
# 4 x 4 default with a sensor (SPEC section 8) at 9/16 of its cost.
SUB_READS = 3
# The slope's baseline, as a share of the family's drawn resolution (drawn_resolution_m).
# Measured (bench/photon_incidence.py, bench/results/photon_incidence.json: the sum over
# sub-rays of cos, the shipped model's 3 x 3 sub-reads against the simulator's 4 x 4 sub-rays,
# 5 aircraft types at 3-6 and 9-12 km and 3 drones, 10 conditions each): over one lidar cell
# the ratios spread 0.83-1.67 (mean |log ratio| 0.163); over 0.5 of a sheet pixel 0.79-1.17
# (0.103); 0.35 and 0.7 of it: 0.137 and 0.109.
SLOPE_BASELINE = 0.5


def sub_ray_lidar(lidar: LidarParams, k: int = SUB_READS) -> LidarParams:
    """The K-times finer lidar whose cell centres are ``lidar``'s K x K sub-ray centres (K
    odd), its window one finer cell wider on each side so every sub-ray of the window fits."""
    return LidarParams(lidar.r_alpha / k, lidar.r_beta / k, lidar.r_r, lidar.width * k + 2,
                       lidar.height * k + 2)


def slope_strides(model, table: np.ndarray, fine: LidarParams, k: int = SUB_READS):
    """Per condition, the strides (finer cells across the row, up the column) of the slope
    that gives a generated sub-ray its incidence: :data:`SLOPE_BASELINE` of the model's drawn
    resolution (``model.drawn_resolution_m(table)``) in metres at the condition's range, at
    least one finer cell; one whole lidar cell (``k`` finer cells) for a family that says
    none."""
    res = model.drawn_resolution_m(table)
    n = len(table)
    if res is None:
        return np.full(n, k, np.int64), np.full(n, k, np.int64)
    base = SLOPE_BASELINE * np.asarray(res, np.float64)
    r0, b0 = table[:, 1], table[:, 2]
    k_w = np.maximum(1, np.rint(base / (r0 * fine.r_alpha * np.cos(b0)))).astype(np.int64)
    k_h = np.maximum(1, np.rint(base / (r0 * fine.r_beta))).astype(np.int64)
    return k_w, k_h


def sub_ray_hits(model, table: np.ndarray, names, lidar: LidarParams,
                 k: int = SUB_READS) -> SubRayHits:
    """The K x K sub-rays of ``model``'s clouds of conditions ``table`` at ``lidar``: the
    model (a family with ``ANY_LIDAR``) draws them at the K-times finer lidar, unquantized.
    The model itself is left as it was (a shallow copy draws)."""
    import copy
    fine_model = copy.copy(model)
    fine = sub_ray_lidar(lidar, k)
    fine_model.lidar = fine
    fine_model.quantize = False
    n = len(table)
    res = fine_model.generate(fine_model.conditions(list(names), table[:, 1:]))
    k_w, k_h = slope_strides(model, table, fine, k)
    hits = hits_of_cloud(res.cloud, table[:, 2], fine, n, stride=k_w, stride_h=k_h)
    half = (k - 1) // 2
    w = np.floor_divide(hits.w.astype(np.int64) + half, k)
    h = np.floor_divide(hits.h.astype(np.int64) + half, k)
    keep = lidar.inside(w, h)
    return SubRayHits(hits.sample[keep], w[keep].astype(np.int32), h[keep].astype(np.int32),
                      hits.range_m[keep], hits.cos[keep], n, k * k)


def photon_generated(cloud: PointCloud, table: np.ndarray, names, lidar: LidarParams, sensor,
                     seed: int, first_id: int, model=None) -> PointCloud:
    """What ``sensor`` records of generated clouds (``cloud.sample`` indexing rows of
    ``table``, types ``names`` per row); cloud i's draws are seeded by (seed, first_id + i).
    With the ``model`` that drew them, when its family draws at any lidar, from its K x K
    sub-rays (:func:`sub_ray_hits`); else one return per point filling its cell."""
    from ..catalog.catalog import default_catalog
    from .reflectivity import reflectivity_of
    from .stage import photon_cloud, to_cloud
    n = len(table)
    cat = default_catalog()
    rho = np.array([reflectivity_of(cat.get(name)) for name in names], np.float64)
    if model is not None and getattr(model, "ANY_LIDAR", False):
        hits = sub_ray_hits(model, table, names, lidar)
    else:
        hits = hits_of_cloud(cloud, table[:, 2], lidar, n)
    cells = photon_cloud(hits, table[:, 1], rho, sensor, lidar, seed,
                         first_id + np.arange(n, dtype=np.int64))
    return to_cloud(cells, table[:, 2], lidar)
