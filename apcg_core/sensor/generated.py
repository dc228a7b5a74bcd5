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
partial, and a cell's ranges keep their spread, as the simulator's sub-rays do.
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


def hits_of_cloud(cloud: PointCloud, elevation: np.ndarray, lidar: LidarParams,
                  n_samples: int, stride: int = 1) -> SubRayHits:
    """One return per point of ``cloud`` (``cloud.sample`` in 0..n_samples-1, ``elevation``
    per sample for the cell heights), its incidence from the range slope between the cells
    ``stride`` cells away on either side."""
    s = (np.zeros(len(cloud), np.int64) if cloud.sample is None
         else np.asarray(cloud.sample, np.int64))
    w = cloud.cell_w.astype(np.int64)
    h = cloud.cell_h.astype(np.int64)
    r = cloud.range_m.astype(np.float64)
    k = int(stride)
    span = lidar.width + 2 * k  # a row of keys with room for the neighbours of the edge cells
    key = (s * (lidar.height + 2 * k) + (h - lidar.h_min + k)) * span + (w - lidar.w_min + k)
    order = np.argsort(key, kind="stable")
    key, s, w, h, r = key[order], s[order], w[order], h[order], r[order]
    dr_w = _slope(r, _neighbour_range(key, key, r, -k), _neighbour_range(key, key, r, k)) / k
    dr_h = _slope(r, _neighbour_range(key, key, r, -k * span),
                  _neighbour_range(key, key, r, k * span)) / k
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


def sub_ray_lidar(lidar: LidarParams, k: int = SUB_READS) -> LidarParams:
    """The K-times finer lidar whose cell centres are ``lidar``'s K x K sub-ray centres (K
    odd), its window one finer cell wider on each side so every sub-ray of the window fits."""
    return LidarParams(lidar.r_alpha / k, lidar.r_beta / k, lidar.r_r, lidar.width * k + 2,
                       lidar.height * k + 2)


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
    # incidence from the slope across one whole cell (K finer cells): the drawn ranges are
    # smooth at the cells' scale, not below it
    hits = hits_of_cloud(res.cloud, table[:, 2], fine, n, stride=k)
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
