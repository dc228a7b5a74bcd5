"""Closed, outward-wound primitives the catalog assembles aircraft from (plain numpy).

Each function returns one closed :class:`Mesh` in the body frame (x nose, y left, z up).
Parts of an aircraft are separate closed shells that may overlap; the lidar sees the first
surface along a ray, so overlaps inside the skin never show.
"""

from __future__ import annotations

import numpy as np

from .mesh import Mesh


def loft(rings: np.ndarray, start_apex=None, end_apex=None) -> Mesh:
    """Skin a sequence of closed rings (K, N, 3) into one closed shell.

    Each end is closed by a fan to an apex point (given, or the ring's centroid), so no
    triangle is degenerate as long as consecutive rings and ring points differ.
    """
    rings = np.asarray(rings, dtype=np.float64)
    k, n, _ = rings.shape
    verts = [rings.reshape(-1, 3)]
    i = np.arange(n)
    j = (i + 1) % n
    faces = []
    for r in range(k - 1):
        a, b = r * n + i, r * n + j
        c, d = (r + 1) * n + j, (r + 1) * n + i
        faces.append(np.stack([a, b, c], 1))
        faces.append(np.stack([a, c, d], 1))
    s_apex = rings[0].mean(axis=0) if start_apex is None else np.asarray(start_apex, float)
    e_apex = rings[-1].mean(axis=0) if end_apex is None else np.asarray(end_apex, float)
    s_idx, e_idx = k * n, k * n + 1
    verts.append(np.stack([s_apex, e_apex]))
    faces.append(np.stack([np.full(n, s_idx), j, i], 1))
    last = (k - 1) * n
    faces.append(np.stack([np.full(n, e_idx), last + i, last + j], 1))
    return Mesh(np.concatenate(verts), np.concatenate(faces)).outward()


def superellipse(n: int, exponent: float = 2.0) -> np.ndarray:
    """Unit superellipse ring (n, 2): |u|^p + |v|^p = 1; p = 2 a circle, larger p boxier."""
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    c, s = np.cos(t), np.sin(t)
    return np.stack([np.sign(c) * np.abs(c) ** (2.0 / exponent),
                     np.sign(s) * np.abs(s) ** (2.0 / exponent)], 1)


def body(stations, n: int = 24, exponent: float = 2.0, axis: str = "x") -> Mesh:
    """A lofted body (fuselage, nacelle, boom) along ``axis``.

    ``stations`` rows are (s, half_width, half_height, centre_a, centre_b): position along the
    axis, the cross-section's half sizes and its centre in the other two axes. The first and
    last rows are the tips (their half sizes are ignored: the body closes to a point there).
    """
    st = np.asarray(stations, dtype=np.float64)
    ring = superellipse(n, exponent)
    rings = []
    for s, hw, hh, ca, cb in st[1:-1]:
        u = ca + hw * ring[:, 0]
        v = cb + hh * ring[:, 1]
        rings.append(_place(s, u, v, axis))
    tip0 = _place(st[0, 0], st[0, 3:4], st[0, 4:5], axis)[0]
    tip1 = _place(st[-1, 0], st[-1, 3:4], st[-1, 4:5], axis)[0]
    return loft(np.stack(rings), tip0, tip1)


def _place(s, u, v, axis):
    s = np.full_like(np.asarray(u, float), s)
    if axis == "x":  # cross-section in (y, z)
        return np.stack([s, u, v], 1)
    if axis == "y":  # cross-section in (x, z)
        return np.stack([u, s, v], 1)
    return np.stack([u, v, s], 1)  # axis z, cross-section in (x, y)


def cylinder(p0, p1, radius: float, n: int = 16, exponent: float = 2.0) -> Mesh:
    """A closed cylinder from p0 to p1 (struts, arms, motors, rotor discs)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axis = p1 - p0
    length = np.linalg.norm(axis)
    a = axis / length
    helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(a, helper)
    u /= np.linalg.norm(u)
    v = np.cross(a, u)
    ring = superellipse(n, exponent) * radius
    base = ring[:, :1] * u + ring[:, 1:] * v
    return loft(np.stack([p0 + base, p1 + base]), p0, p1)


def box(centre, size) -> Mesh:
    """Axis-aligned box."""
    c, s = np.asarray(centre, float), np.asarray(size, float) / 2
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * s + c
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return Mesh(corners, faces).outward()


def airfoil(n_side: int = 10, thickness: float = 0.12) -> np.ndarray:
    """Symmetric NACA 4-digit section (2 n_side, 2) in chord units: x from 0 (LE) to 1 (TE).

    The closed-trailing-edge form: one TE point and one LE point, upper then lower surface.
    """
    beta = np.linspace(0.0, np.pi, n_side + 1)
    x = 0.5 * (1.0 - np.cos(beta))  # cosine spacing, 0 .. 1
    t = thickness
    yt = 5 * t * (0.2969 * np.sqrt(x) - 0.1260 * x - 0.3516 * x**2 + 0.2843 * x**3
                  - 0.1036 * x**4)
    upper = np.stack([x[::-1], yt[::-1]], 1)  # TE -> LE
    lower = np.stack([x[1:-1], -yt[1:-1]], 1)  # after LE -> before TE
    return np.concatenate([upper[:-1], upper[-1:], lower])


def lifting_surface(stations, thickness: float = 0.12, n_side: int = 10,
                    vertical: bool = False) -> Mesh:
    """A wing, tailplane or fin lofted through spanwise stations.

    ``stations`` rows are (x_le, s, h, chord): leading-edge x, spanwise coordinate s and the
    out-of-plane coordinate h, and the local chord. For a horizontal surface s is y and h is z;
    for a vertical one (``vertical``) s is z and h is y. Give stations from one tip to the
    other (or root to tip); the ends are closed by fans.
    """
    st = np.asarray(stations, dtype=np.float64)
    sec = airfoil(n_side, thickness)
    rings = []
    for x_le, s, h, chord in st:
        x = x_le - sec[:, 0] * chord  # chord runs aft (-x) from the leading edge
        thick = h + sec[:, 1] * chord
        span = np.full_like(x, s)
        rings.append(np.stack([x, thick, span], 1) if vertical else np.stack([x, span, thick], 1))
    return loft(np.stack(rings))
