"""What every ray caster answers in the same terms: hits from float32 distances, and each
ray's first surface (distance and triangle) for the photon stage."""

from __future__ import annotations

import numpy as np


def hits_of(distances32, origin: np.ndarray, direction: np.ndarray,
            t_max: float) -> tuple[np.ndarray, np.ndarray]:
    """A caster's ``cast_hits`` from its ``distances32`` (float32 t in units of each float32
    direction's length, exactly the limit on a miss): (ray index, float64 distance) of the hits.

    Misses (three rays in four) are dropped before any float64 work."""
    if len(origin) == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    limit = np.float32(t_max)
    t32 = distances32(origin, direction, limit)
    # A hit has t * |d| < limit (1 - 1e-6) with |d| within 1e-7 of 1, so t < limit.
    ray = np.flatnonzero(t32 < limit)
    t = t32[ray].astype(np.float64)
    t *= np.sqrt((direction[ray].astype(np.float64) ** 2).sum(axis=1))
    hit = is_hit(t, limit)
    return ray[hit], t[hit]


def is_hit(t: np.ndarray, limit) -> np.ndarray:
    """A distance short of the ray's length (by more than float32 rounding) is a hit."""
    return t < float(limit) * (1.0 - 1e-6)


def surface_hits(caster, origin: np.ndarray, direction: np.ndarray,
                 t_max: float) -> tuple[np.ndarray, np.ndarray]:
    """Distance (float64, inf where none) and triangle index (-1 where none) of each ray's
    first surface: what the photon stage needs (range and incidence). A caster answers both at
    once where it can (``surfaces``); otherwise ``cast`` gives the distances and ``triangles``
    the hit rays' triangles."""
    if hasattr(caster, "surfaces"):
        return caster.surfaces(origin, direction, t_max)
    t = caster.cast(origin, direction, t_max)
    tri = np.full(len(t), -1, np.int64)
    hit = np.flatnonzero(np.isfinite(t))
    if len(hit):
        o = np.ascontiguousarray(origin[hit], dtype=np.float32)
        d = np.ascontiguousarray(direction[hit], dtype=np.float32)
        tri[hit] = caster.triangles(o, d, np.float32(t_max))
    return t, tri
