"""Float64 ranges where a float32 ray caster's answer is too close to a time-bin edge.

A ray caster answers in float32: embree and Blender each round the distance to the first
surface their own way, a few micrometres apart (more at grazing incidence). Quantization (SPEC
section 4: the range goes to the centre of its 0.15 m time bin) turns those micrometres into a
whole bin wherever the range lies within them of a bin edge: 30 cells in 2.9 million on the
bench's shards (bench/blender_path.py) came out one bin apart between the backends. So for the
hits within :data:`EDGE_TOL_M` of an edge, the caster is asked only which triangle it hit
(along the float32 ray it was given), and the distance to that triangle is computed here, in
float64, along the float64 cell-centre ray (:func:`rays.cell_rays`) to the mesh's float64
vertices: the same number whichever caster found the triangle, and the exact one to ~1e-12 m.
(Until stop 55 to the vertices rounded to float32 as the casters hold them, which moved a
range by up to a few um: 9 of 13.58 M ranges one 0.15 m bin off on a 102,400-sample build,
5% of cells at 1 um bins; until stop 54 along the float32 ray, whose 1-2 um of rounding, up
to ~0.1 mm at grazing incidence, put about 3 in 100,000 ranges in the bin next to the exact
one: tests/test_refine.py.) Two casters that pick different triangles at a shared edge get
distances ~1e-12 m apart, which no longer straddle a bin edge in practice.

One ray per cell (supersample 1) only: a supersampled cell's range is the nearest of k x k rays.
"""

from __future__ import annotations

import numpy as np

from .rays import cell_rays

# Hits whose range lies this close to a bin edge get the float64 distance. Float32 casters
# differ by micrometres, grazing rays by more: on the 2.9 M hits of bench/blender_path.py's
# shards embree and Blender differ by 1 um (median), 65 um (99.99th percentile), 0.6 mm at
# most, and embree from the float64 distance by 0.5 mm at most. 1 mm of 0.15 m bins sends
# ~1.3 % of the hits here.
EDGE_TOL_M = 1e-3


def near_bin_edges(range_m: np.ndarray, bin_m: float, tol_m: float = EDGE_TOL_M) -> np.ndarray:
    """Indices of the ranges within ``tol_m`` of a multiple of ``bin_m`` (a time-bin edge)."""
    q = np.asarray(range_m, dtype=np.float64) / bin_m
    q -= np.round(q)  # signed distance to the nearest edge, in bins
    return np.flatnonzero(np.abs(q) < tol_m / bin_m)


def triangle_distances(vertices: np.ndarray, faces: np.ndarray, tri: np.ndarray,
                       origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Float64 distance (metres) along each ray (``origin``, ``direction``: float64, or float32
    taken as they are) to the plane of its triangle ``tri`` (Moller-Trumbore in float64, on
    the mesh's float64 ``vertices``), NaN where ``tri`` is -1, the
    ray is parallel to the plane, or the crossing lies clearly outside the triangle."""
    n = len(tri)
    out = np.full(n, np.nan)
    ok = tri >= 0
    if not ok.any():
        return out
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)[tri[ok]]
    v0, v1, v2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    o = np.asarray(origin, dtype=np.float64)[ok]
    d = np.asarray(direction, dtype=np.float64)[ok]
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(d, e2)
    det = (e1 * p).sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - v0
        u = (s * p).sum(axis=1) * inv
        q = np.cross(s, e1)
        w = (d * q).sum(axis=1) * inv
        t = (e2 * q).sum(axis=1) * inv  # in units of |d|
    # The caster said this triangle (along its float32 ray); only a crossing far outside it (a
    # different surface, a degenerate triangle) is refused. Edge hits sit at u, v ~ 0 and may
    # fall either side, the float64 ray being ~1e-7 rad from the float32 one.
    slack = 1e-6
    inside = (np.isfinite(t) & (u >= -slack) & (w >= -slack) & (u + w <= 1.0 + slack))
    out[ok] = np.where(inside, t * np.sqrt((d * d).sum(axis=1)), np.nan)
    return out


def refine_ranges(caster, vertices: np.ndarray, faces: np.ndarray, table: np.ndarray,
                  lidar, m: np.ndarray, c: np.ndarray, radius: float, s: np.ndarray,
                  w: np.ndarray, h: np.ndarray, r: np.ndarray) -> np.ndarray:
    """``r`` (float64 ranges of the hit cells (s, w, h), one ray per cell) with the hits near a
    time-bin edge replaced by the float64 distance to the triangle the caster hit. Casters
    without ``triangles`` are left as they are."""
    if not hasattr(caster, "triangles"):
        return r
    idx = near_bin_edges(r, lidar.r_r, EDGE_TOL_M)
    if len(idx) == 0:
        return r
    si = s[idx]
    # the rays the build cast, rounded to float32 as its blocks round them
    origin, direction, t_start, t_max = cell_rays(table[si], w[idx], h[idx], lidar, m[si],
                                                  c[si], radius)
    o32 = origin.astype(np.float32)
    d32 = direction.astype(np.float32)
    tri = caster.triangles(o32, d32, np.float32(t_max))
    # the distance along the exact (float64) ray: the bin is decided in float64 (SPEC section 4)
    exact = t_start + triangle_distances(vertices, faces, tri, origin, direction)
    ok = np.isfinite(exact) & (np.abs(exact - r[idx]) < EDGE_TOL_M)
    out = r.copy()
    out[idx[ok]] = exact[ok]
    return out
