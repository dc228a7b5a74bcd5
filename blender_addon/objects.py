"""Lidars and targets as Blender objects, and the pose of a target relative to its lidar.

A lidar is an Empty carrying ``apcg_lidar`` properties; the lidar looks along its local +Y with
local +Z up (SPEC section 2). A target is a mesh in the body frame (the object's local frame),
parented to a lidar, with its pose kept twice: as the object's matrix (float32: what the user
sees and moves) and as double-precision custom properties (what scans and generation use, so a
target at 18 km is placed to the micrometre). :func:`pose_of` takes the doubles while the
matrix still agrees with them, and the matrix once the user has moved the object.
"""

from __future__ import annotations

import math

import bpy
import numpy as np
from mathutils import Matrix

from apcg_core.catalog import default_catalog
from apcg_core.errors import InputError
from apcg_core.frames import POSE_NAMES, pose_from_lidar_local, target_matrix_lidar_local
from apcg_core.lidar import LidarParams

LIDAR_KEY = "apcg_lidar_params"  # marks a lidar (the PropertyGroup holds the values)
# The pose as named doubles {range_m, elevation, pitch, yaw, roll, azimuth} (m, rad): names, not
# positions. Files of add-on 0.x stored a list in the order below; they are read by it once.
POSE_KEY = "apcg_pose"
_LEGACY_POSE_ORDER = ("range_m", "elevation", "azimuth", "yaw", "pitch", "roll")
TYPE_KEY = "apcg_type"  # the type's catalog name (or the name of your own model): its identity
LENGTH_KEY = "apcg_depth_length_m"
# The object matrix is float32: it agrees with the doubles to ~1e-7 relative. A larger
# difference means the user moved the object.
_MOVED_TOL_M = 1e-3
_MOVED_TOL_REL = 1e-6


def is_lidar(obj) -> bool:
    return obj is not None and obj.get(LIDAR_KEY) is not None


def is_target(obj) -> bool:
    return obj is not None and obj.get(POSE_KEY) is not None


def lidar_of(obj):
    """The lidar a target (or cloud) belongs to: its parent when that is a lidar."""
    if is_lidar(obj):
        return obj
    parent = obj.parent if obj is not None else None
    return parent if is_lidar(parent) else None


def lidar_params(lidar) -> LidarParams:
    p = lidar.apcg_lidar
    # the UI stores float32; round to what a person types so 0.004 deg stays 0.004 deg
    return LidarParams.from_degrees(round(p.r_alpha_deg, 7), round(p.r_beta_deg, 7),
                                    round(p.range_resolution_m, 7), int(p.width),
                                    int(p.height))


def add_lidar(name: str = "APCG Lidar", params: LidarParams | None = None,
              location=(0.0, 0.0, 0.0), rotation_euler=(0.0, 0.0, 0.0), collection=None):
    """A lidar Empty in ``collection`` (default: the scene's), looking along its local +Y."""
    params = params or LidarParams.from_degrees()
    obj = bpy.data.objects.new(name, None)
    obj.empty_display_type = "ARROWS"
    obj.empty_display_size = 2.0
    obj.location = location
    obj.rotation_euler = rotation_euler
    obj[LIDAR_KEY] = 1
    p = obj.apcg_lidar
    p.r_alpha_deg = math.degrees(params.r_alpha)
    p.r_beta_deg = math.degrees(params.r_beta)
    p.range_resolution_m = params.r_r
    p.width, p.height = params.width, params.height
    (collection or bpy.context.scene.collection).objects.link(obj)
    return obj


def mesh_from_arrays(name: str, vertices: np.ndarray, faces: np.ndarray):
    """A Blender mesh of triangles, filled with foreach_set (fast for large meshes)."""
    me = bpy.data.meshes.new(name)
    n_v, n_f = len(vertices), len(faces)
    me.vertices.add(n_v)
    me.vertices.foreach_set("co", np.asarray(vertices, np.float32).ravel())
    me.loops.add(3 * n_f)
    me.loops.foreach_set("vertex_index", np.asarray(faces, np.int32).ravel())
    me.polygons.add(n_f)
    me.polygons.foreach_set("loop_start", np.arange(0, 3 * n_f, 3, dtype=np.int32))
    if bpy.app.version < (4, 0, 0):  # read-only (derived from loop_start) from 4.0 on
        me.polygons.foreach_set("loop_total", np.full(n_f, 3, np.int32))
    me.update()
    me.validate()
    return me


def triangles_of(obj, depsgraph=None):
    """(vertices float64 (V, 3), faces int (F, 3)) of an object's evaluated mesh, local frame."""
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(depsgraph)
    me = ev.to_mesh()
    try:
        me.calc_loop_triangles()
        verts = np.zeros(3 * len(me.vertices), np.float32)
        me.vertices.foreach_get("co", verts)
        tris = np.zeros(3 * len(me.loop_triangles), np.int32)
        me.loop_triangles.foreach_get("vertices", tris)
    finally:
        ev.to_mesh_clear()
    return verts.reshape(-1, 3).astype(np.float64), tris.reshape(-1, 3)


class _Mesh:  # what the simulator needs of a mesh
    def __init__(self, vertices, faces):
        self.vertices, self.faces = vertices, faces


def body_mesh(obj, depsgraph=None) -> _Mesh:
    v, f = triangles_of(obj, depsgraph)
    if len(f) == 0:
        raise InputError(f"target {obj.name!r} has no faces to scan")
    return _Mesh(v, f)


def _check_pose(range_m, elevation, pitch, yaw, roll, azimuth) -> list[float]:
    vals = [float(v) for v in (range_m, elevation, pitch, yaw, roll, azimuth)]
    for name, v in zip(POSE_NAMES, vals, strict=True):
        if not math.isfinite(v):
            raise InputError(f"{name} must be finite, got {v!r}")
    if vals[0] <= 0:
        raise InputError(f"range_m must be > 0, got {vals[0]!r}")
    if abs(vals[1]) >= math.pi / 2:
        raise InputError(f"elevation must be inside (-90, 90) deg, got {math.degrees(vals[1])}")
    return vals


def set_pose(obj, range_m, elevation, pitch=0.0, yaw=0.0, roll=0.0, azimuth=0.0) -> None:
    """Place a target relative to its lidar (metres, radians; the angles in the project's one
    order, POSE_NAMES); keeps the exact doubles."""
    vals = _check_pose(range_m, elevation, pitch, yaw, roll, azimuth)
    m = target_matrix_lidar_local(*vals)
    obj[POSE_KEY] = dict(zip(POSE_NAMES, vals, strict=True))
    obj.matrix_parent_inverse.identity()
    obj.matrix_basis = Matrix([list(row) for row in m])  # rows (a bare list means columns)


def _matrix_of(obj) -> np.ndarray:
    return np.array([list(row) for row in obj.matrix_basis], dtype=np.float64)


def _stored_pose(obj) -> dict:
    stored = obj[POSE_KEY]
    if hasattr(stored, "to_dict"):
        return {k: float(stored[k]) for k in POSE_NAMES}
    return {k: float(v) for k, v in zip(_LEGACY_POSE_ORDER, stored, strict=True)}


def pose_moved(obj) -> bool:
    """True when the object's matrix no longer agrees with its stored pose."""
    pose = _stored_pose(obj)
    p = [pose[k] for k in POSE_NAMES]
    m = target_matrix_lidar_local(*p)
    got = _matrix_of(obj)
    tol = _MOVED_TOL_M + _MOVED_TOL_REL * p[0]
    return bool(np.abs(got[:3, 3] - m[:3, 3]).max() > tol
                or np.abs(got[:3, :3] - m[:3, :3]).max() > 1e-5)


def pose_of(obj) -> dict:
    """The target's pose: a dict of POSE_NAMES (m and rad)."""
    if not is_target(obj):
        raise InputError(f"{obj.name!r} is not an APCG target (add one with apcg.add_aircraft)")
    if not pose_moved(obj):
        return _stored_pose(obj)
    return pose_from_lidar_local(_matrix_of(obj))


def sync_pose(obj) -> bool:
    """Store the pose of a moved target as its doubles; True if it had moved."""
    if is_target(obj) and pose_moved(obj):
        obj[POSE_KEY] = pose_from_lidar_local(_matrix_of(obj))
        return True
    return False


def simulator_row(obj) -> np.ndarray:
    """The target's pose as the simulator's one-row table [0, r0, beta0, pitch, yaw, roll]
    (m, rad). The simulator is handed the target's own mesh, so the type column is unused and
    left 0; a type crosses to a model by its name (TYPE_KEY), never by a code."""
    p = pose_of(obj)
    return np.array([[0.0, p["range_m"], p["elevation"], p["pitch"], p["yaw"], p["roll"]]])


def add_aircraft(lidar, type_name: str, range_m: float, elevation_deg: float,
                 pitch_deg: float = 0.0, yaw_deg: float = 0.0, roll_deg: float = 0.0,
                 azimuth_deg: float = 0.0, catalog=None, name: str | None = None):
    """A catalog type (by name or index) as a target of ``lidar`` at the given pose."""
    if not is_lidar(lidar):
        raise InputError(f"{getattr(lidar, 'name', lidar)!r} is not an APCG lidar "
                         "(add one with apcg.add_lidar)")
    catalog = catalog or default_catalog()
    t = catalog.get(type_name)
    mesh = catalog.mesh(t)
    me = mesh_from_arrays(t.name, mesh.vertices, mesh.faces)
    obj = bpy.data.objects.new(name or t.name, me)
    obj[TYPE_KEY] = t.name
    obj[LENGTH_KEY] = float(catalog.depth_length_m(t))
    _link_like(obj, lidar)
    obj.parent = lidar
    set_pose(obj, range_m, *(math.radians(v) for v in (elevation_deg, pitch_deg, yaw_deg,
                                                        roll_deg, azimuth_deg)))
    return obj


def make_target(lidar, obj, range_m: float, elevation_deg: float, pitch_deg: float = 0.0,
                yaw_deg: float = 0.0, roll_deg: float = 0.0, azimuth_deg: float = 0.0,
                depth_length_m: float | None = None):
    """Turn an existing mesh object (your own model, local frame = body frame: x nose, y left
    wing, z up, origin at the centre of mass) into a target of ``lidar``."""
    if obj.type != "MESH":
        raise InputError(f"{obj.name!r} is a {obj.type}, not a mesh")
    v, _ = triangles_of(obj)
    obj[TYPE_KEY] = obj.get(TYPE_KEY, obj.name)
    obj[LENGTH_KEY] = float(depth_length_m or (v[:, 0].max() - v[:, 0].min()))
    obj.parent = lidar
    set_pose(obj, range_m, *(math.radians(v) for v in (elevation_deg, pitch_deg, yaw_deg,
                                                        roll_deg, azimuth_deg)))
    return obj


def targets_of(lidar, selected_only: bool = False) -> list:
    kids = [o for o in lidar.children if is_target(o)]
    if selected_only:
        kids = [o for o in kids if o.select_get()]
    return kids


def _link_like(obj, other) -> None:
    cols = list(other.users_collection) or [bpy.context.scene.collection]
    cols[0].objects.link(obj)
