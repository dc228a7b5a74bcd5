"""Import of real models (OFF, OBJ, STL, PLY, glTF/GLB) into the body frame, and export.

trimesh is imported here, when used (the `sim` extra). OFF is parsed by our own reader
because ModelNet's files break other readers: CRLF line ends, and a first line where "OFF"
runs into the counts ("OFF490 518 0").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .mesh import Mesh

AXES = {"X": (0, 1.0), "Y": (1, 1.0), "Z": (2, 1.0),
        "-X": (0, -1.0), "-Y": (1, -1.0), "-Z": (2, -1.0)}
FORMATS = (".off", ".obj", ".stl", ".ply", ".glb", ".gltf")


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


def _trimesh():
    try:
        import trimesh
    except ImportError as exc:
        raise InputError("importing and exporting models needs trimesh: "
                         "pip install 'apcg[sim]'") from exc
    return trimesh


def read_off(path: Path) -> Mesh:
    """ModelNet-tolerant OFF reader (polygons are fan-triangulated)."""
    text = path.read_bytes().decode("utf-8", errors="replace").replace("\r", "")
    tokens_lines = [ln.split("#")[0].strip() for ln in text.split("\n")]
    lines = [ln for ln in tokens_lines if ln]
    if not lines or not lines[0].upper().startswith("OFF"):
        raise InputError(f"{path}: not an OFF file (the first line does not start with 'OFF')")
    head = lines[0][3:].split()  # "OFF490 518 0" keeps its counts on the first line
    body = lines[1:]
    if not head:
        head, body = body[0].split(), body[1:]
    try:
        nv, nf = int(head[0]), int(head[1])
        verts = np.array([ln.split()[:3] for ln in body[:nv]], dtype=np.float64)
        faces = []
        for ln in body[nv:nv + nf]:
            idx = [int(v) for v in ln.split()]
            k = idx[0]
            poly = idx[1:1 + k]
            faces += [[poly[0], poly[i], poly[i + 1]] for i in range(1, k - 1)]
    except (ValueError, IndexError) as exc:
        raise InputError(f"{path}: corrupt OFF file ({exc})") from exc
    if len(verts) != nv or not faces:
        raise InputError(f"{path}: corrupt OFF file (expected {nv} vertices and {nf} faces)")
    return Mesh(verts, np.array(faces))


def read_mesh(path) -> Mesh:
    """Read a mesh file as it is stored (no unit or axis change), all bodies concatenated."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise InputError(f"{path}: the file is empty")
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise InputError(f"{path}: unsupported format {suffix!r}; accepted: {', '.join(FORMATS)}")
    if suffix == ".off":
        mesh = read_off(path)
    else:
        trimesh = _trimesh()
        try:
            loaded = trimesh.load(str(path), process=False, force="mesh")
        except Exception as exc:  # trimesh raises many types on bad files
            raise InputError(f"{path}: cannot read the file ({type(exc).__name__}: {exc})") \
                from exc
        if not hasattr(loaded, "faces") or len(loaded.faces) == 0:
            raise InputError(f"{path}: the file holds no triangles")
        mesh = Mesh(np.asarray(loaded.vertices), np.asarray(loaded.faces))
    if len(mesh.faces) == 0 or not np.isfinite(mesh.vertices).all():
        raise InputError(f"{path}: the mesh is empty or has non-finite coordinates")
    return mesh


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
    """Weld duplicate vertices (STL and many OBJ files store triangles unshared)."""
    scale = float(np.abs(mesh.vertices).max()) or 1.0
    key = np.round(mesh.vertices / (scale * 1e-9)).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[mesh.faces]
    f0, f1, f2 = faces.T
    keep = (f0 != f1) & (f1 != f2) & (f0 != f2)
    return Mesh(mesh.vertices[first], faces[keep])


def import_model(path, forward: str = "X", up: str = "Z", unit_scale: float | None = None,
                 length_m: float | None = None, centre: bool = True):
    """Load a model into the body frame (x nose, y left, z up), in metres.

    Scale either by ``unit_scale`` (file units -> metres) or so the length along the nose axis
    is ``length_m``. With ``centre`` the origin moves to the volume centroid when the mesh is
    closed, else to the bounding-box centre (SPEC section 2). Returns ``(Mesh, ImportReport)``.
    """
    if unit_scale is not None and length_m is not None:
        raise InputError("give either unit_scale or length_m, not both")
    mesh = _merge_close(read_mesh(path))
    mesh = mesh.transformed(axis_matrix(forward, up))
    ext = mesh.extents
    if length_m is not None:
        if not np.isfinite(length_m) or length_m <= 0:
            raise InputError(f"length_m must be > 0, got {length_m!r}")
        if ext[0] <= 0:
            raise InputError(f"{path}: the model has no extent along its forward axis")
        scale = float(length_m) / float(ext[0])
    else:
        scale = 1.0 if unit_scale is None else float(unit_scale)
        if not np.isfinite(scale) or scale <= 0:
            raise InputError(f"unit_scale must be > 0, got {unit_scale!r}")
    mesh = mesh.transformed(np.eye(3) * scale)
    rep = mesh.report()
    how = "none"
    if centre:
        if rep.watertight and abs(rep.volume) > 0:
            mesh = mesh.outward()
            origin, how = mesh.centroid, "volume centroid"
        else:
            origin, how = mesh.bounds.mean(axis=0), "bounding-box centre"
        mesh = mesh.transformed(offset=-origin)
    report = ImportReport(str(path), len(mesh.vertices), len(mesh.faces), rep.n_bodies,
                          rep.watertight, how, scale, tuple(float(e) for e in mesh.extents))
    return mesh, report


def export_mesh(mesh: Mesh, path) -> Path:
    """Write the mesh (body frame, metres) as PLY, OBJ, STL or GLB, by the file's suffix."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".obj", ".stl", ".glb"):
        raise InputError(f"{path}: unsupported export format {suffix!r}; accepted: .ply, .obj, "
                         ".stl, .glb")
    trimesh = _trimesh()
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    data = tm.export(file_type=suffix[1:])
    tmp.write_bytes(data.encode() if isinstance(data, str) else data)
    tmp.replace(path)  # never a half-written file under the final name
    return path
