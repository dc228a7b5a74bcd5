"""Checks on an imported model: is its size plausible, which axes does it look like it has, and
how much of it does a lidar see through holes.

Size limits (SPEC section 2): the largest extent of an aircraft is 1-100 m (the catalog's
smallest crewed type is 6 m, the largest 84 m); of a drone 2 cm-10 m.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..errors import InputError
from .mesh import Mesh, sample_surface

SIZE_LIMITS_M = {"aircraft": (1.0, 100.0), "drone": (0.02, 10.0)}
TYPICAL_SIZE_M = {"aircraft": 20.0, "drone": 0.6}
# Units a model file is often in, metres per unit; for the hint when a size is implausible.
COMMON_UNITS = (("millimetres", 0.001), ("centimetres", 0.01), ("inches", 0.0254),
                ("decimetres", 0.1), ("feet", 0.3048), ("metres", 1.0))


def size_problem(extents_m, kind: str, unit_scale_applied: float = 1.0) -> str | None:
    """None when the largest extent is plausible for ``kind``; else what is wrong and the
    likely fix. ``unit_scale_applied``: the metres-per-file-unit the size came from."""
    if kind not in SIZE_LIMITS_M:
        raise InputError(f"kind must be one of {', '.join(SIZE_LIMITS_M)}, got {kind!r}")
    lo, hi = SIZE_LIMITS_M[kind]
    size = float(np.max(extents_m))
    if not math.isfinite(size):
        return f"its size is not finite ({size!r})"
    if lo <= size <= hi:
        return None
    article = "an" if kind[0] in "aeiou" else "a"
    shown = f"{size:.0f}" if size >= 1000 else f"{size:.4g}"
    msg = f"it is {shown} m across, implausible for {article} {kind} (accepted {lo:g}-{hi:g} m)"
    in_file_units = size / unit_scale_applied
    fits = [(abs(math.log(in_file_units * f / TYPICAL_SIZE_M[kind])), name, f)
            for name, f in COMMON_UNITS if lo <= in_file_units * f <= hi]
    if fits:
        _, name, f = min(fits)
        msg += f"; it looks like {name}: --unit-scale {f:g}"
    other = next((k for k, (a, b) in SIZE_LIMITS_M.items() if k != kind and a <= size <= b),
                 None)
    if other is not None:  # a 0.5 m quadcopter added with the default kind
        msg += f"; if it is {'an' if other[0] in 'aeiou' else 'a'} {other}: --kind {other}"
    return msg + ("; or give its length in metres with --length-m; to add it at this size "
                  "anyway, give --force (which also replaces your type of the same name)")


def check_size(extents_m, kind: str, force: bool = False, unit_scale_applied: float = 1.0,
               name: str = "the model") -> str | None:
    """Refuse an implausible size (InputError) unless ``force``; with ``force`` return the
    problem as a warning to print."""
    problem = size_problem(extents_m, kind, unit_scale_applied)
    if problem and not force:
        raise InputError(f"{name}: {problem}")
    return problem


def nearest_distance(points: np.ndarray, probe: np.ndarray, chunk: int = 512) -> np.ndarray:
    """Distance from each probe point to its nearest point: scipy's k-d tree when installed,
    else numpy by brute force in chunks (Blender's own Python has no scipy); the same values."""
    try:
        from scipy.spatial import cKDTree
    except ImportError:
        sq = (points * points).sum(axis=1)
        out = np.empty(len(probe))
        for i in range(0, len(probe), chunk):
            q = probe[i:i + chunk]
            d2 = (q * q).sum(axis=1)[:, None] + sq[None, :] - 2.0 * q @ points.T
            out[i:i + chunk] = np.sqrt(np.maximum(d2.min(axis=1), 0.0))
        return out
    return cKDTree(points).query(probe)[0]


def _mirror_error(points: np.ndarray, axis: int, other: np.ndarray | None = None) -> float:
    """How far the points are from being mirror-symmetric across the mid-plane normal to
    ``axis``, as a fraction of the model's size (0 = a perfect mirror). With ``other`` (a
    second sample of the same surface), the part of it that sampling alone gives (the
    distance from ``other`` to ``points``, unmirrored) is taken off."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    size = np.max(hi - lo) + 1e-30
    probe = points if other is None else other
    mirrored = probe.copy()
    mirrored[:, axis] = lo[axis] + hi[axis] - mirrored[:, axis]
    err = float(np.mean(nearest_distance(points, mirrored)) / size)
    if other is not None:
        err -= float(np.mean(nearest_distance(points, other)) / size)
    return err


# A mirror error this small (a fraction of the model's size) is what two samples of one
# surface differ by (boxes: up to 3e-4 either way): a box, or a model symmetric both ways,
# gives it across either axis. The least real asymmetry seen: a quadcopter's 0.004.
MIRROR_NOISE = 0.002
EXTENT_TIE = 0.01  # two extents this close (relative) do not tell which one is up


class AxesGuess(NamedTuple):
    forward: str
    up: str
    why: str
    confident: bool  # the mirror plane stood out clearly (not a box or a multirotor)


def guess_axes(mesh: Mesh, n: int = 4000) -> AxesGuess:
    """A guess of the file axes from the shape of an aircraft.

    Up: the axis of the smallest extent (aircraft and drones are flatter than they are long or
    wide). Span: of the two others, the one across which the model is a mirror image. Forward:
    the third, signed so that the highest points (fin, tail rotor) lie aft. A guess: right for
    27 of 30 models tried (the catalog's every fourth type, the shared reference meshes and
    the tests' box aircraft; wrong for one helicopter and two multirotors, which look alike
    from every side). Check it with ``catalog add --preview``."""
    pts = sample_surface(mesh, n, seed=0)
    other = sample_surface(mesh, n, seed=1)
    ext = pts.max(axis=0) - pts.min(axis=0)
    up = int(np.argmin(ext))
    a, b = [i for i in range(3) if i != up]
    errs = {a: _mirror_error(pts, a, other), b: _mirror_error(pts, b, other)}
    span = min(errs, key=errs.get)
    fwd = b if span == a else a
    # Up is taken as +: a rotor disc or a multirotor's body on top outweighs any sign cue.
    top = pts[pts[:, up] >= pts[:, up].max() - 0.15 * ext[up]]  # never empty
    fwd_sign = -1.0 if np.mean(top[:, fwd]) > np.median(pts[:, fwd]) else 1.0
    names = "XYZ"
    forward = ("-" if fwd_sign < 0 else "") + names[fwd]
    upname = names[up]
    why = (f"smallest extent along {names[up]}, mirror-symmetric across {names[span]} "
           f"(asymmetry {errs[span]:.3f} against {errs[fwd]:.3f}), highest parts aft")
    small = np.sort(ext)[:2]
    decided = small[1] - small[0] > EXTENT_TIE * small[1]  # else argmin picks X on a tie
    confident = decided and errs[fwd] > MIRROR_NOISE and errs[span] < 0.5 * errs[fwd] - 1e-4
    return AxesGuess(forward, upname, why, bool(confident))


def axes_fix(guess: AxesGuess | None, forward: str, up: str, forward_given: bool = False,
             up_given: bool = False, default_forward=None) -> dict[str, str]:
    """The axis options that would turn ``forward`` / ``up`` (the file axes used) into the
    ones a *confident* ``guess`` from the shape suggests, where they contradict it: ``{"up":
    "Z"}``, ``{"forward": "-Y"}``, both, or ``{}`` when they agree (or the guess is unsure).

    Only axes are compared, not their signs (the guess's sign of forward, from the tallest
    parts lying aft, is a weaker cue; up is taken as +). Axes the user gave
    (``forward_given`` / ``up_given``) are not questioned. ``default_forward(up)``: the forward
    that a changed up would bring with it when forward is not given (the importer's rule)."""
    if guess is None or not guess.confident:
        return {}
    fix = {}
    if not up_given and up.lstrip("-").upper() != guess.up.lstrip("-"):
        fix["up"] = guess.up
        if not forward_given and default_forward is not None:
            forward = default_forward(guess.up)
    if not forward_given and forward.lstrip("-").upper() != guess.forward.lstrip("-"):
        fix["forward"] = guess.forward
    return fix


def axes_warning(guess: AxesGuess | None, forward: str, up: str, used: str = "",
                 option=lambda k, v: f"--{k} {v}", **kwargs) -> str | None:
    """One line when the axes used contradict a confident guess from the shape (see
    :func:`axes_fix`), naming the option(s) that fix it: ``option(name, axis)`` spells one
    for the caller (the command line's ``--up Z``, the add-on's ``Up Z``). ``used``: the
    axes used and where they came from, as the caller shows them."""
    fix = axes_fix(guess, forward, up, **kwargs)
    if not fix:
        return None
    fixes = " ".join(option(k, v) for k, v in sorted(fix.items(), reverse=True))
    used = used or f"forward {forward.upper()}, up {up.upper()}"
    return (f"the axes used ({used}) contradict the shape, which looks like forward "
            f"{guess.forward}, up {guess.up} ({guess.why}): the model would lie on its side "
            f"or turned; use {fixes} (check with a preview)")


def _directions() -> np.ndarray:
    """The 6 axis and 8 diagonal view directions: every side of the model, evenly."""
    axes = np.vstack([np.eye(3), -np.eye(3)])
    diag = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    return np.vstack([axes, diag / np.sqrt(3.0)])


def hole_entry_share(mesh: Mesh, grid: int = 96) -> dict:
    """The share of rays that reach the model's inside through a hole, at a standard pose.

    Parallel rays in a ``grid`` x ``grid`` raster from 14 directions (each side and diagonal).
    A ray's first hit is on the inside of a surface when the surface faces away from it. Each
    connected part is first wound consistently and turned so that most of its first hits are
    on its outside; a part whose first hits are nearly half inside and half outside is a
    single-sided sheet (a plate, a rotor disc), seen from both sides, and is not counted.
    Returns ``{"share", "rays_hit", "inside_hits", "sheets"}``; ``share`` above 0.01 means a
    lidar sees into the model (open windows, missing panels)."""
    try:
        import trimesh
    except ImportError as exc:
        raise InputError("the open-mesh check needs trimesh: pip install 'apcg[sim]'") from exc
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    trimesh.repair.fix_winding(tm)
    labels = trimesh.graph.connected_component_labels(tm.face_adjacency,
                                                      node_count=len(tm.faces))
    normals = np.cross(tm.vertices[tm.faces[:, 1]] - tm.vertices[tm.faces[:, 0]],
                       tm.vertices[tm.faces[:, 2]] - tm.vertices[tm.faces[:, 0]])
    centre = tm.bounds.mean(axis=0)
    radius = float(np.linalg.norm(tm.extents)) / 2 * 1.01 + 1e-9
    s = (np.arange(grid) + 0.5) / grid * 2 - 1
    uu, vv = [g.ravel() * radius for g in np.meshgrid(s, s)]
    hit_face, hit_dir = [], []
    for d in _directions():
        u = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(d, u)
        origins = centre - 2 * radius * d + uu[:, None] * u + vv[:, None] * v
        dirs = np.broadcast_to(d, origins.shape)
        tri = tm.ray.intersects_first(origins, dirs)
        tri = tri[tri >= 0]
        hit_face.append(tri)
        hit_dir.append(np.broadcast_to(d, (len(tri), 3)))
    faces = np.concatenate(hit_face)
    dirs = np.concatenate(hit_dir)
    if len(faces) == 0:
        return {"share": 0.0, "rays_hit": 0, "inside_hits": 0, "sheets": 0}
    inside = np.einsum("ij,ij->i", normals[faces], dirs) > 0
    part = labels[faces]
    n_parts = int(labels.max()) + 1
    hits = np.bincount(part, minlength=n_parts)
    backs = np.bincount(part, weights=inside, minlength=n_parts)
    flip = backs > hits / 2  # a part wound inside out: its outside is what most rays meet
    inside = inside ^ flip[part]
    backs = np.where(flip, hits - backs, backs)
    sheet = (hits > 0) & (backs > 0.35 * hits)
    counted = inside & ~sheet[part]
    return {"share": float(counted.mean()), "rays_hit": int(len(faces)),
            "inside_hits": int(counted.sum()), "sheets": int(sheet.sum())}
