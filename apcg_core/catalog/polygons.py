"""Polygon faces (OBJ, PLY, OFF n-gons) into triangles that stay inside each polygon.

Readers fan-triangulate a polygon from its first corner, (0, i, i + 1): right for a convex
polygon, but for a concave one (an L-shaped cap whose first corner is not the reflex one) the
fan lays triangles over the notch, surface that is not there. Where the fan is right the fan is
kept (so every file imports as it always did); where it is not, the polygon is ear-clipped in
its own plane.
"""

from __future__ import annotations

import numpy as np


def _plane_frame(pts: np.ndarray):
    """Newell normals of polygons ``pts`` (n, k, 3): the area vector (twice the area long),
    robust to a polygon that is not quite planar."""
    c = pts - pts.mean(axis=1, keepdims=True)
    return np.cross(c, np.roll(c, -1, axis=1)).sum(axis=1)


def fans_wrong(vertices: np.ndarray, polys: np.ndarray) -> np.ndarray:
    """Per polygon of ``polys`` (n, k >= 4 corners, one size), True where the fan from the first
    corner is not its triangulation: one fan triangle turns against the polygon's normal (it
    lies outside the polygon). Polygons with no area keep their fan."""
    pts = vertices[polys]
    normal = _plane_frame(pts)
    a = pts[:, 1:-1] - pts[:, :1]
    b = pts[:, 2:] - pts[:, :1]
    turn = np.einsum("nij,nj->ni", np.cross(a, b), normal)  # each fan triangle's area x 4A
    norm2 = np.einsum("ij,ij->i", normal, normal)
    return turn.min(axis=1) < -1e-9 * norm2


def _in_plane(pts: np.ndarray) -> np.ndarray:
    """(k, 2) coordinates of a polygon in its plane, counter-clockwise about its normal."""
    n = _plane_frame(pts[None])[0]
    n = n / (np.linalg.norm(n) or 1.0)
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    c = pts - pts.mean(axis=0)
    return np.stack([c @ u, c @ w], axis=1)


def _turn(o, a, b) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _is_ear(p, idx, j) -> bool:
    n = len(idx)
    a, b, c = idx[j - 1], idx[j], idx[(j + 1) % n]
    if _turn(p[a], p[b], p[c]) <= 0:  # reflex or flat corner: not an ear
        return False
    for q in idx:
        if q in (a, b, c) or any((p[q] == p[r]).all() for r in (a, b, c)):
            continue
        if _turn(p[a], p[b], p[q]) >= 0 and _turn(p[b], p[c], p[q]) >= 0 \
                and _turn(p[c], p[a], p[q]) >= 0:
            return False  # another corner inside: cutting this ear would cross the outline
    return True


def ear_clip(p: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangles (corner numbers, in the polygon's own order, so each keeps its winding) of a
    simple polygon ``p`` (k, 2), counter-clockwise. A self-intersecting outline has no true
    ear at some step; then the first convex corner (else the first corner) is cut."""
    idx = list(range(len(p)))
    tris = []
    while len(idx) > 3:
        n = len(idx)
        j = next((j for j in range(n) if _is_ear(p, idx, j)), None)
        if j is None:
            j = next((j for j in range(n)
                      if _turn(p[idx[j - 1]], p[idx[j]], p[idx[(j + 1) % n]]) > 0), 0)
        tris.append((idx[j - 1], idx[j], idx[(j + 1) % n]))
        idx.pop(j)
    tris.append(tuple(idx))
    return tris


def triangulate_polygons(vertices: np.ndarray, polys) -> np.ndarray:
    """(F, 3) triangles of polygons ``polys`` (lists of vertex indices, 3 or more each), in
    their order: the fan (0, i, i + 1) where it is right, the ear clipping where it is not."""
    vertices = np.asarray(vertices, np.float64)
    wrong = set()
    by_size: dict[int, list[int]] = {}
    for n, poly in enumerate(polys):
        if len(poly) > 3:
            by_size.setdefault(len(poly), []).append(n)
    for ns in by_size.values():
        arr = np.array([polys[n] for n in ns], np.int64)
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite: refused later
            bad = fans_wrong(vertices, arr)
        wrong.update(np.array(ns)[bad].tolist())
    faces = []
    for n, poly in enumerate(polys):
        if n in wrong:
            local = ear_clip(_in_plane(vertices[list(poly)]))
            faces += [[poly[a], poly[b], poly[c]] for a, b, c in local]
        else:
            faces += [[poly[0], poly[i], poly[i + 1]] for i in range(1, len(poly) - 1)]
    return np.array(faces, np.int64).reshape(-1, 3)


def wrong_fans(vertices: np.ndarray, polys) -> bool:
    """Whether any polygon of ``polys`` would be fanned outside itself."""
    vertices = np.asarray(vertices, np.float64)
    by_size: dict[int, list] = {}
    for poly in polys:
        if len(poly) > 3:
            by_size.setdefault(len(poly), []).append(poly)
    with np.errstate(invalid="ignore", over="ignore"):
        return any(fans_wrong(vertices, np.array(ps, np.int64)).any()
                   for ps in by_size.values())
