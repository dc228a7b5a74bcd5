"""The photon stage on a generated (or any one-point-per-cell) cloud (SPEC section 8).

A generator draws the standard cloud: one range per cell, no sub-rays and no surface normals.
Each point becomes one return filling its cell (K = 1), and its incidence is read off the
cloud itself: the range's slope across neighbouring cells (centred differences where both
neighbours exist, one-sided at an edge, flat with none) gives the surface normal, and
cos = 1 / sqrt(1 + (dr/dx)^2 + (dr/dy)^2) with dx, dy the cell's width and height at that
range. Partial cells (a wing edge across a cell) cannot be told apart and count as full.
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
                  n_samples: int) -> SubRayHits:
    """One return per point of ``cloud`` (``cloud.sample`` in 0..n_samples-1, ``elevation``
    per sample for the cell heights), its incidence from the range slope."""
    s = (np.zeros(len(cloud), np.int64) if cloud.sample is None
         else np.asarray(cloud.sample, np.int64))
    w = cloud.cell_w.astype(np.int64)
    h = cloud.cell_h.astype(np.int64)
    r = cloud.range_m.astype(np.float64)
    span = lidar.width + 2  # a row of keys with room for the neighbours of the edge cells
    key = (s * (lidar.height + 2) + (h - lidar.h_min + 1)) * span + (w - lidar.w_min + 1)
    order = np.argsort(key, kind="stable")
    key, s, w, h, r = key[order], s[order], w[order], h[order], r[order]
    dr_w = _slope(r, _neighbour_range(key, key, r, -1), _neighbour_range(key, key, r, 1))
    dr_h = _slope(r, _neighbour_range(key, key, r, -span), _neighbour_range(key, key, r, span))
    beta = np.asarray(elevation, np.float64)[s] + h * lidar.r_beta
    dx = r * lidar.r_alpha * np.cos(beta)
    dy = r * lidar.r_beta
    cos = 1.0 / np.sqrt(1.0 + (dr_w / dx) ** 2 + (dr_h / dy) ** 2)
    # key order is sample, then row, then column: grouped by sample as the stage wants
    return SubRayHits(s, w.astype(np.int32), h.astype(np.int32), r, cos, n_samples, 1)


def photon_generated(cloud: PointCloud, table: np.ndarray, names, lidar: LidarParams, sensor,
                     seed: int, first_id: int) -> PointCloud:
    """What ``sensor`` records of generated clouds (``cloud.sample`` indexing rows of
    ``table``, types ``names`` per row); cloud i's draws are seeded by (seed, first_id + i)."""
    from ..catalog.catalog import default_catalog
    from .reflectivity import reflectivity_of
    from .stage import photon_cloud, to_cloud
    n = len(table)
    cat = default_catalog()
    rho = np.array([reflectivity_of(cat.get(name)) for name in names], np.float64)
    hits = hits_of_cloud(cloud, table[:, 2], lidar, n)
    cells = photon_cloud(hits, table[:, 1], rho, sensor, lidar, seed,
                         first_id + np.arange(n, dtype=np.int64))
    return to_cloud(cells, table[:, 2], lidar)
