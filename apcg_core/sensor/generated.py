"""The photon stage on a generated (or any one-point-per-cell) cloud (SPEC section 8).

A generator draws the standard cloud: one range per cell, no sub-rays and no surface normals.
Each point becomes one return filling its cell (K = 1), and its incidence is read off the
cloud itself: the range's slope to the neighbouring cells gives the surface normal, and
cos = 1 / sqrt(1 + (dr/dx)^2 + (dr/dy)^2) with dx, dy the cell's width and height at that
range. Along each direction the slope is the centred difference where the two one-sided
differences agree (same sign, neither more than :data:`AGREE` times the other), else the
smaller of them: a neighbour on another surface (a wing in front of the fuselage, a tail
behind it) is a jump in range, not a tilt, and the centred difference across it would read a
grazing cell where the surface faces the lidar. One-sided at an edge, flat with no neighbour.
Partial cells (a wing edge across a cell) cannot be told apart and count as full.

A family that draws at any lidar's cells (``ANY_LIDAR``: APCG+ reads its sheet at them) gives
sub-rays instead (issue 33): it draws the same conditions at the K-times finer lidar
(K = :data:`SUB_READS`, odd, so that the finer cells' centres are exactly the K x K centred
sub-ray grid of SPEC section 4), unquantized; each finer point is one sub-ray of its cell with
its own range, and its incidence from the slope across finer cells
(:func:`sub_rays_of_fine_cloud`; the simulator's own clouds at the finer lidar, read the same
way, check this path: bench/photon_path.py). Partial cells then count as partial, and a
cell's ranges keep their spread, as the simulator's sub-rays do.
"""

from __future__ import annotations

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError
from ..lidar import FinerLidar, LidarParams
from .stage import SubRayHits


def _neighbour_range(key: np.ndarray, sorted_keys: np.ndarray, ranges: np.ndarray,
                     offset: int) -> np.ndarray:
    """The range at key + offset, NaN where that cell has no point."""
    want = key + offset
    at = np.minimum(np.searchsorted(sorted_keys, want), len(sorted_keys) - 1)
    found = sorted_keys[at] == want
    return np.where(found, ranges[at], np.nan)


# Two one-sided range differences "agree" (one surface: their mean is the slope) when they
# have the same sign and neither is more than this many times the other; else one of them
# crosses to another surface and the smaller is the slope. 4 from bench/photon_path.py
# --agree A on exact geometry, seven aircraft types at 3-6 km: the cells' signal correlates
# 0.95-0.99 with the simulator's true normals', sums -5% to +7%; 2 and 8 gave the same
# correlation with sums -3% to +10% and -6% to +6%; never averaging across a sign change
# alone (A = 1000) gave 0.94-0.98 and -8% to -1%.
AGREE = 4.0


def _slope(r: np.ndarray, minus: np.ndarray, plus: np.ndarray) -> np.ndarray:
    """The range's change per cell from the neighbours' ranges (NaN: no neighbour): the
    centred difference where the one-sided ones agree (:data:`AGREE`), else the smaller of
    them (a jump to another surface is not a tilt); one-sided at an edge, 0 alone."""
    ahead = plus - r
    behind = r - minus
    small = np.where(np.abs(ahead) < np.abs(behind), ahead, behind)
    lo = np.minimum(np.abs(ahead), np.abs(behind))
    agree = (ahead * behind > 0) & (np.maximum(np.abs(ahead), np.abs(behind)) <= AGREE * lo)
    both = np.where(agree, (ahead + behind) / 2.0, small)
    return np.where(np.isnan(ahead), np.nan_to_num(behind),
                    np.where(np.isnan(behind), ahead, both))


def hits_of_cloud(cloud: PointCloud, elevation: np.ndarray, lidar: LidarParams,
                  n_samples: int, cos: np.ndarray | None = None) -> SubRayHits:
    """One return per point of ``cloud`` (``cloud.sample`` in 0..n_samples-1, ``elevation``
    per sample for the cell heights), its incidence from the range slope to the neighbouring
    cells (:func:`_slope`), or each point's ``cos`` where given (a model's incidence
    output)."""
    s = (np.zeros(len(cloud), np.int64) if cloud.sample is None
         else np.asarray(cloud.sample, np.int64))
    w = cloud.cell_w.astype(np.int64)
    h = cloud.cell_h.astype(np.int64)
    r = cloud.range_m.astype(np.float64)
    span = lidar.width + 2  # a row of keys with room for the neighbours of the edge cells
    key = (s * (lidar.height + 2) + (h - lidar.h_min + 1)) * span + (w - lidar.w_min + 1)
    order = np.argsort(key, kind="stable")
    key, s, w, h, r = key[order], s[order], w[order], h[order], r[order]
    if cos is not None:
        cos = np.clip(np.asarray(cos, np.float64)[order], 0.0, 1.0)
        return SubRayHits(s, w.astype(np.int32), h.astype(np.int32), r, cos, n_samples, 1)
    dr_w = _slope(r, _neighbour_range(key, key, r, -1), _neighbour_range(key, key, r, 1))
    dr_h = _slope(r, _neighbour_range(key, key, r, -span), _neighbour_range(key, key, r, span))
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
    try:
        return FinerLidar(lidar.r_alpha / k, lidar.r_beta / k, lidar.r_r, lidar.width * k + 2,
                          lidar.height * k + 2)
    except InputError as exc:  # the user gave `lidar`, not this one: say why it is refused
        raise InputError(
            f"with a sensor, a model draws {k} x {k} sub-rays a cell in a window one finer "
            f"cell wider on each side, which the lidar ({lidar.describe()}) cannot hold: "
            f"{exc}. Accepted: width x r_alpha_deg + {2 / k:.3g} r_alpha_deg < 180 deg and "
            f"height x r_beta_deg + {2 / k:.3g} r_beta_deg < 90 deg") from None


def sub_ray_hits(model, table: np.ndarray, names, lidar: LidarParams,
                 k: int = SUB_READS) -> SubRayHits:
    """The K x K sub-rays of ``model``'s clouds of conditions ``table`` at ``lidar``: the
    model (a family with ``ANY_LIDAR``) draws them at the K-times finer lidar, unquantized
    (:func:`fine_hits`), each finer point a sub-ray of the cell it falls in."""
    return cells_of_fine_hits(fine_hits(model, table, names, lidar, k), lidar, k)


def sub_ray_model(model, lidar: LidarParams, k: int = SUB_READS):
    """A shallow copy of ``model`` that draws ``lidar``'s K x K sub-rays: at
    ``sub_ray_lidar(lidar, k)``, unquantized, by the model's rule for sub-rays (APCG+: the
    threshold, :meth:`apcg_core.families.plus_draw.Draw.at_sub_rays`)."""
    import copy
    fine_model = copy.copy(model)
    fine_model.lidar = sub_ray_lidar(lidar, k)
    fine_model.quantize = False
    if hasattr(fine_model, "draw"):
        fine_model.draw = fine_model.draw.at_sub_rays()
    return fine_model


def fine_hits(model, table: np.ndarray, names, lidar: LidarParams,
              k: int = SUB_READS) -> SubRayHits:
    """``model``'s returns of conditions ``table`` at ``sub_ray_lidar(lidar, k)``, one per
    finer cell, unquantized, drawn by the model's rule for sub-rays (APCG+: the threshold,
    :meth:`apcg_core.families.plus_draw.Draw.at_sub_rays`); each one's incidence is the
    model's incidence output where it has one (``draws_incidence``), else the range slope's.
    The model itself is left as it was (a shallow copy draws)."""
    fine_model = sub_ray_model(model, lidar, k)
    res = fine_model.generate(fine_model.conditions(list(names), table[:, 1:]))
    cos = (fine_model.incidence_of(res.table, res.cloud)
           if getattr(model, "draws_incidence", False) else None)
    return hits_of_cloud(res.cloud, table[:, 2], fine_model.lidar, len(table), cos)


def sub_rays_of_fine_cloud(cloud: PointCloud, elevation: np.ndarray, lidar: LidarParams,
                           n_samples: int, k: int = SUB_READS,
                           cos: np.ndarray | None = None) -> SubRayHits:
    """``lidar``'s K x K sub-rays from a cloud drawn at ``sub_ray_lidar(lidar, k)``: each
    finer point one sub-ray of the cell it falls in, its incidence ``cos`` where given (per
    point), else from the slope across finer cells (:func:`hits_of_cloud`); points outside
    ``lidar``'s window are left out."""
    return cells_of_fine_hits(hits_of_cloud(cloud, elevation, sub_ray_lidar(lidar, k),
                                            n_samples, cos), lidar, k)


def cells_of_fine_hits(hits: SubRayHits, lidar: LidarParams, k: int = SUB_READS) -> SubRayHits:
    """Returns at ``sub_ray_lidar(lidar, k)``'s cells as sub-rays of ``lidar``'s cells (the
    finer cell whose centre lies in a cell is one of its K x K sub-rays); outside ``lidar``'s
    window left out."""
    half = (k - 1) // 2
    w = np.floor_divide(hits.w.astype(np.int64) + half, k)
    h = np.floor_divide(hits.h.astype(np.int64) + half, k)
    keep = lidar.inside(w, h)
    return SubRayHits(hits.sample[keep], w[keep].astype(np.int32), h[keep].astype(np.int32),
                      hits.range_m[keep], hits.cos[keep], hits.n_samples, k * k)


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
