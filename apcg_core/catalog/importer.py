"""Import of real models into the body frame, in metres, and export.

Which reader takes which file, and what each file declares of its unit and axes, is the table
in ``formats.py``. Here: axes, unit and centre are applied, in that order of precedence for
each: the user's option, else what the file declares, else the default (x forward, z up,
metres), and the result is reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.atomic import atomic_path
from .formats import SUFFIXES, _trimesh, read_model
from .mesh import Mesh

AXES = {"X": (0, 1.0), "Y": (1, 1.0), "Z": (2, 1.0),
        "-X": (0, -1.0), "-Y": (1, -1.0), "-Z": (2, -1.0)}
FORMATS = SUFFIXES


@dataclass
class ImportReport:
    path: str
    n_vertices: int
    n_faces: int
    n_bodies: int
    watertight: bool
    centre: str  # "volume centroid" or "bounding-box centre"
    scale: float  # factor applied to the file's units
    extents_m: tuple[float, float, float]  # length (x), span (y), height (z)
    unit: str = ""  # where the scale came from
    axes: str = ""  # where forward and up came from
    objects: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    guess: object = None  # checks.AxesGuess: the file axes the shape suggests
    forward: str = "X"  # the file axes used
    up: str = "Z"
    axes_declared: bool = False  # the file declares its axes (glTF, COLLADA, Blender-read)
    forward_declared: bool = False
    n_dropped: int = 0  # degenerate (zero-area) triangles dropped
    n_duplicates: int = 0  # triangles on the same three vertices as another, dropped
    precision: str | None = None  # what float32 coordinates far from the origin lost


def read_mesh(path) -> Mesh:
    """Read a mesh file as it is stored (no unit or axis change), all bodies concatenated."""
    return read_model(path).mesh


def axis_matrix(forward: str = "X", up: str = "Z") -> np.ndarray:
    """Rotation taking the file's ``forward`` axis to body +x (nose) and ``up`` to +z."""
    try:
        fi, fs = AXES[forward.upper()]
        ui, us = AXES[up.upper()]
    except KeyError as exc:
        raise InputError(f"axis {exc.args[0]!r} unknown; accepted: {', '.join(AXES)}") from exc
    if fi == ui:
        raise InputError(f"forward {forward!r} and up {up!r} must be different axes")
    fwd = np.zeros(3)
    fwd[fi] = fs
    upv = np.zeros(3)
    upv[ui] = us
    left = np.cross(upv, fwd)
    return np.stack([fwd, left, upv])  # rows: body x, y, z expressed in file axes


def _merge_close(mesh: Mesh) -> Mesh:
    """Weld duplicate vertices (STL and many OBJ files store triangles unshared): those within
    1e-9 of the model's size of each other, measured from its bounding-box centre (not the
    file's origin: a model stored kilometres away would be welded on a grid of millimetres)."""
    if not len(mesh.vertices):
        return mesh
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    scale = float(np.max(hi - lo)) or 1.0
    key = np.round((mesh.vertices - (lo + hi) / 2) / (scale * 1e-9)).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[mesh.faces]
    f0, f1, f2 = faces.T
    keep = (f0 != f1) & (f1 != f2) & (f0 != f2)
    return Mesh(mesh.vertices[first], faces[keep])


def drop_duplicates(mesh: Mesh) -> tuple[Mesh, int, bool]:
    """``(mesh, n, closed)``: where the mesh is closed once triangles on the same three
    vertices as an earlier one (in any order or winding) are gone, the mesh without them and
    how many went; else the mesh as it was (a sheet modelled double-sided keeps both sides).
    Exporters leave copies; a kept copy puts its edges in three or four faces, so a closed
    mesh would read as open and be centred on its bounding box, not its volume centroid."""
    if not len(mesh.faces):
        return mesh, 0, False
    _, first = np.unique(np.sort(mesh.faces, axis=1), axis=0, return_index=True)
    if len(first) == len(mesh.faces):
        return mesh, 0, mesh.is_watertight()
    unique = Mesh(mesh.vertices, mesh.faces[np.sort(first)])
    if not unique.is_watertight():
        return mesh, 0, False
    return unique, len(mesh.faces) - len(first), True


FLOAT32_SPACING_M = 1e-3  # float32 coordinates further apart than this lose the shape


def float32_precision(raw, scale: float) -> str | None:
    """What a file of float32 coordinates (binary STL, glTF, PLY float) lost where its model
    lies so far from the file's origin that neighbouring float32 values are more than 1 mm
    apart (UTM coordinates: 0.5 m): the import is exact, the file is not; None where fine."""
    if raw.float32_max is None or not np.isfinite(raw.float32_max):
        return None
    step = float(np.spacing(np.float32(raw.float32_max))) * scale
    if step <= FLOAT32_SPACING_M:
        return None
    return (f"its coordinates are 32-bit floats up to {raw.float32_max:.4g} from the file's "
            f"origin, where they are {step * 1000:.3g} mm apart: the shape has lost that "
            "precision in the file itself; move the model to the origin before exporting "
            "(or export OBJ, whose coordinates keep every digit)")


DEGENERATE_AREA = 1e-12  # a triangle's area, relative to the model's size squared


def drop_degenerate(mesh: Mesh, path, n_read: int | None = None) -> tuple[Mesh, int]:
    """The mesh without its zero-area triangles (three points on a line, or two in one
    place), and how many were dropped; a mesh with nothing else is refused by name
    (``n_read``: the triangles the file held, where some were already merged away).
    Non-finite coordinates are refused too (docs/IMPORT.md)."""
    bad = ~np.isfinite(mesh.vertices).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"{path}: {int(bad.sum())} vertices have non-finite coordinates "
                         f"(the first, vertex {i + 1}: {mesh.vertices[i].tolist()}); fix or "
                         "remove them in a modeller")
    used = mesh.vertices[np.unique(mesh.faces)] if len(mesh.faces) else mesh.vertices[:0]
    size = float(np.max(used.max(axis=0) - used.min(axis=0))) if len(used) else 0.0
    with np.errstate(over="ignore", invalid="ignore"):
        areas = mesh.face_areas
        keep = areas > DEGENERATE_AREA * size * size
    if not np.isfinite(areas).all():
        raise InputError(f"{path}: coordinates too large to compute with (up to "
                         f"{float(np.abs(used).max()):.3g}); scale the model down in a modeller")
    if not keep.any():
        n = len(mesh.faces) if n_read is None else n_read
        which = "its one triangle has" if n == 1 else f"every one of its {n} triangles has"
        raise InputError(f"{path}: {which} zero area (its points lie on a line or a point): "
                         "there is no surface to import")
    return used_only(Mesh(mesh.vertices, mesh.faces[keep])), int((~keep).sum())


FLAT_THICKNESS = 1e-6  # the thinnest direction, relative to the largest: below it, flat


def check_not_flat(mesh: Mesh, path) -> None:
    """Refuse a model whose triangles all lie in one plane (a sheet of zero thickness in
    every direction of that plane's normal): no aircraft or drone is, its extents and
    centre of volume are undefined, and a lidar sees it edge-on as nothing."""
    v = mesh.vertices - mesh.vertices.mean(axis=0)
    s = np.linalg.svd(v, compute_uv=False) if len(v) >= 3 else np.zeros(3)
    if len(s) < 3 or s[-1] <= FLAT_THICKNESS * s[0]:
        n = len(mesh.faces)
        which = "its one triangle lies" if n == 1 else f"its {n} triangles all lie"
        raise InputError(f"{path}: the model is flat: {which} in one plane (zero "
                         "thickness); an aircraft or drone model needs "
                         "three dimensions (a fuselage, a fin): there is no body to import")


def used_only(mesh: Mesh) -> Mesh:
    """The mesh without vertices that no triangle uses (they would count in its extents)."""
    used, faces = np.unique(mesh.faces, return_inverse=True)
    if len(used) == len(mesh.vertices):
        return mesh
    return Mesh(mesh.vertices[used], faces.reshape(-1, 3))


def _default_forward(up: str) -> str:
    return "X" if up.upper().lstrip("-") != "X" else "Y"


def import_model(path, forward: str | None = None, up: str | None = None,
                 unit_scale: float | None = None, length_m: float | None = None,
                 centre: bool = True, objects: str | None = None, guess: bool = False):
    """Load a model into the body frame (x nose, y left, z up), in metres.

    Axes: ``forward`` / ``up`` name the file's nose and up axes; where not given, what the file
    declares (glTF: +Z front, +Y up; COLLADA: its up_axis; Blender-read formats: Z up), else x
    forward and z up. Size: ``length_m`` (the nose-to-tail length), else ``unit_scale`` (file
    units -> metres), else the unit the file declares, else metres. With ``centre`` the origin
    moves to the volume centroid when the mesh is closed, else to the bounding-box centre (SPEC
    section 2). ``objects``: comma-separated name patterns of the objects to take. With
    ``guess`` the report also holds the file axes the shape suggests (checks.guess_axes).
    Returns ``(Mesh, ImportReport)``."""
    if unit_scale is not None and length_m is not None:
        raise InputError("give either unit_scale or length_m, not both")
    raw = read_model(path, objects)
    n_read = len(raw.mesh.faces)
    mesh = _merge_close(used_only(raw.mesh))
    # closed is decided before zero-area triangles go: one that seals a T-junction (an edge
    # split on one side only, as CAD exporters leave) is part of a closed surface
    mesh, n_duplicates, sealed = drop_duplicates(mesh)
    mesh, _ = drop_degenerate(mesh, path, n_read)
    check_not_flat(mesh, path)
    n_dropped = n_read - n_duplicates - len(mesh.faces)
    guessed = None
    if guess:
        from .checks import guess_axes
        guessed = guess_axes(mesh)
    axes_from = []
    for label, given, declared, default in (("up", up, raw.up, "Z"),
                                            ("forward", forward, raw.forward, None)):
        if given is not None:
            axes_from.append(f"{label} {given} (given)")
        elif declared is not None:
            axes_from.append(f"{label} {declared} (the file)")
        else:
            axes_from.append(f"{label} {default or _default_forward(up or raw.up or 'Z')} "
                             "(default)")
    if up is not None and forward is None and raw.forward is not None \
            and up.upper().lstrip("-") == raw.forward.upper().lstrip("-"):
        raise InputError(f"{path}: the file declares forward {raw.forward} (up {raw.up}), "
                         f"the axis of your --up {up}: give --forward too (X, -X, Y, -Y, Z, "
                         "-Z)")
    up = up or raw.up or "Z"
    forward = forward or raw.forward or _default_forward(up)
    mesh = mesh.transformed(axis_matrix(forward, up))
    ext = mesh.extents
    if length_m is not None:
        if not np.isfinite(length_m) or length_m <= 0:
            raise InputError(f"length_m must be > 0, got {length_m!r}")
        if ext[0] <= 0:
            raise InputError(f"{path}: the model has no extent along its forward axis")
        scale = float(length_m) / float(ext[0])
        unit = f"scaled to --length-m {length_m:g}"
    elif unit_scale is not None:
        scale = float(unit_scale)
        if not np.isfinite(scale) or scale <= 0:
            raise InputError(f"unit_scale must be > 0, got {unit_scale!r}")
        unit = f"--unit-scale {scale:g}"
    elif raw.unit_m is not None:
        scale, unit = float(raw.unit_m), raw.unit_note
    else:
        scale, unit = 1.0, "not declared by the file: metres assumed"
    mesh = mesh.transformed(np.eye(3) * scale)
    rep = mesh.report()
    closed = rep.watertight or sealed
    how = "none"
    if centre:
        if closed and abs(rep.volume) > 0:
            mesh, turned = mesh.bodies_outward()
            origin, how = mesh.centroid, "volume centroid"
            if turned:
                how += (f"; {turned} of its {rep.n_bodies} bodies were wound inward and were "
                        "turned outward")
        else:
            origin, how = mesh.bounds.mean(axis=0), "bounding-box centre"
        mesh = mesh.transformed(offset=-origin)
    report = ImportReport(str(path), len(mesh.vertices), len(mesh.faces), rep.n_bodies,
                          closed, how, scale, tuple(float(e) for e in mesh.extents),
                          unit, ", ".join(reversed(axes_from)), raw.objects, raw.skipped,
                          guessed, forward, up, raw.up is not None or raw.forward is not None,
                          raw.forward is not None, n_dropped, n_duplicates,
                          float32_precision(raw, scale))
    return mesh, report


def export_mesh(mesh: Mesh, path) -> Path:
    """Write the mesh (body frame, metres) as PLY, OBJ, STL or GLB, by the file's suffix:
    PLY, OBJ and STL in the body frame's own axes (x nose, z up), glTF in the axes its
    specification states (+Y up, +Z forward, metres), so `catalog add` reads each back at the
    same size and attitude."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in EXPORT_SUFFIXES:
        raise InputError(f"{path}: unsupported export format {suffix!r}; accepted: "
                         f"{', '.join(EXPORT_SUFFIXES)}")
    trimesh = _trimesh()
    vertices = mesh.vertices
    if suffix in FILE_AXES:  # the format's own axes (glTF: +Y up, +Z forward, +X left)
        vertices = vertices @ axis_matrix(*FILE_AXES[suffix])  # body = A @ file
    tm = trimesh.Trimesh(vertices, mesh.faces, process=False)
    data = tm.export(file_type=suffix[1:])
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


EXPORT_SUFFIXES = (".ply", ".obj", ".stl", ".glb")
# (forward, up) of export formats whose specification fixes their axes; the others declare
# none and are read back as written (x forward, z up), so every export reads back as it was.
FILE_AXES = {".glb": ("Z", "Y")}
