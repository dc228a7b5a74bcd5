"""Lidars and targets as Blender objects, and the pose of a target relative to its lidar.

A lidar is an Empty carrying ``apcg_lidar`` properties; the lidar looks along its local +Y with
local +Z up (SPEC section 2). A target is a mesh in the body frame (the object's local frame),
parented to a lidar, with its pose kept twice: as the object's matrix (float32: what the user
sees and moves) and as double-precision custom properties (what scans and generation use, so a
target at 18 km is placed to the micrometre). :func:`pose_of` takes the doubles while the
matrix still agrees with them, and the matrix once the user has moved the object.
"""

from __future__ import annotations

import functools
import math
from contextlib import contextmanager
from dataclasses import dataclass

import bpy
import numpy as np
from mathutils import Matrix

from apcg_core.catalog import default_catalog
from apcg_core.catalog.mesh import Mesh
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
# A target made from a scene object (make_target): how its body frame was found, as
# {forward, up, how ("guessed" / "stated" / ...), why, confident, centre}, and the object itself
# (an ID pointer: the same physical object, so it never occludes its own target's scan).
AXES_KEY = "apcg_axes"
SOURCE_KEY = "apcg_source_object"
AXIS_NAMES = ("X", "-X", "Y", "-Y", "Z", "-Z")
# The object matrix is float32: it agrees with the doubles to ~1e-7 relative. A larger
# difference means the user moved the object.
_MOVED_TOL_M = 1e-3
_MOVED_TOL_REL = 1e-6


# What the add-on makes in bpy.data, removed again when the call that made it fails (objects
# first: they use the meshes).
MADE_KINDS = ("objects", "collections", "meshes", "node_groups", "materials")


def _data_now() -> dict:
    return {k: {x.as_pointer() for x in getattr(bpy.data, k)} for k in MADE_KINDS}


def _remove_made_since(before: dict) -> None:
    for k in MADE_KINDS:
        store = getattr(bpy.data, k)
        for x in [x for x in store if x.as_pointer() not in before[k]]:
            store.remove(x)


_GUARDED = [0]  # calls inside one: the outermost takes the one snapshot and cleans up


@contextmanager
def nothing_left_on_error():
    """A block whose failure leaves bpy.data as it found it: every object, collection, mesh,
    node group and material made inside is removed again before the error goes on (a refused
    import, a scan that fails on its second target...). Yields the snapshot taken before, or
    None inside another such block (scan -> scan_target), which leaves the cleaning to the
    outermost: bpy.data is listed once per call."""
    if _GUARDED[0]:
        yield None
        return
    before = _data_now()
    _GUARDED[0] += 1
    try:
        yield before
    except BaseException:
        _remove_made_since(before)
        raise
    finally:
        _GUARDED[0] -= 1


def leaves_nothing_on_error(fn):
    """:func:`nothing_left_on_error` around every call of ``fn`` (the API's functions)."""
    @functools.wraps(fn)
    def call(*args, **kwargs):
        with nothing_left_on_error():
            return fn(*args, **kwargs)
    return call


def cancelled_leaves_nothing(execute):
    """An operator's ``execute`` whose {'CANCELLED'} (an error it reported) also removes what
    it made on the way (a lidar it added for a target it then refused)."""
    @functools.wraps(execute)
    def run(self, context):
        with nothing_left_on_error() as before:
            result = execute(self, context)
            if before is not None and "CANCELLED" in result:
                _remove_made_since(before)
            return result
    return run


def removed(obj) -> bool:
    """Whether ``obj`` is a Blender object (or other ID) that was deleted since it was handed
    out: every read of it raises Blender's ReferenceError."""
    if not isinstance(obj, bpy.types.ID):
        return False
    try:
        obj.name  # noqa: B018 - the read is the test
    except ReferenceError:
        return True
    return False


def is_lidar(obj) -> bool:
    return isinstance(obj, bpy.types.Object) and not removed(obj) and \
        obj.get(LIDAR_KEY) is not None


def carries_pose(obj) -> bool:
    return isinstance(obj, bpy.types.Object) and not removed(obj) and \
        obj.get(POSE_KEY) is not None


def is_target(obj) -> bool:
    """A mesh object carrying a pose: only a mesh has a surface to scan (an Empty that was
    given the property by a copy is not a target)."""
    return carries_pose(obj) and obj.type == "MESH"


def named(obj) -> str:
    """How a message names what it was given: an object's name, else the value itself."""
    if removed(obj):
        return f"a deleted Blender {type(obj).__name__.lower()} (no longer in the file)"
    return repr(obj.name) if isinstance(obj, bpy.types.ID) else repr(obj)


def require_lidar(obj):
    """``obj`` if it is an APCG lidar; else an InputError naming what was given."""
    if removed(obj):
        raise InputError(f"the lidar given is {named(obj)}: give a lidar of the scene, or add "
                         "one with apcg.add_lidar")
    if not is_lidar(obj):
        raise InputError(f"{named(obj)} is not an APCG lidar (add one with apcg.add_lidar)")
    return obj


def require_target(obj, lidar: bool = True):
    """``obj`` if it is an APCG target (``lidar``: parented to a lidar, directly or through
    other objects); else an InputError naming it."""
    if carries_pose(obj) and not is_target(obj):
        raise InputError(f"{obj.name!r} carries an APCG pose ({POSE_KEY}) but is a "
                         f"{obj.type.lower()}, not a mesh: only a mesh object can be a target "
                         "(remove the property, or make a target of a mesh with "
                         "apcg.make_target)")
    if not is_target(obj):
        raise InputError(f"{named(obj)} is not an APCG target (add one with "
                         "apcg.add_aircraft, or make one from a mesh with apcg.make_target)")
    if lidar and lidar_of(obj) is None:
        raise InputError(f"target {obj.name!r} is not parented to an APCG lidar (directly, or "
                         "through other objects)")
    return obj


def lidar_of(obj):
    """The lidar a target (or cloud) belongs to: its nearest lidar ancestor (an Empty between
    them, a rig, keeps it the lidar's)."""
    while isinstance(obj, bpy.types.Object):
        if is_lidar(obj):
            return obj
        obj = obj.parent
    return None


# The lidar object's values, by their panel property: what Scan, Write Lidar File and Read
# Lidar File take, within the panel's limits (a script or a hand-edited custom property is not
# clamped by Blender).
LIDAR_VALUES = ("r_alpha_deg", "r_beta_deg", "range_resolution_m", "width", "height")


def check_lidar_values(lidar, values: dict, where: str) -> None:
    """Refuse (InputError naming ``where``, the property, its panel label and limits) a value
    of ``values`` (panel property name -> value) that the lidar object's panel does not take."""
    props = lidar.apcg_lidar.bl_rna.properties
    for name, v in values.items():
        prop = props[name]
        real = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        whole = prop.type != "INT" or (real and v == int(v))
        if real and whole and prop.hard_min <= v <= prop.hard_max:
            continue
        how = ("more than" if real and v > prop.hard_max else
               "less than" if real and v < prop.hard_min else "not what")
        kind = "an integer" if prop.type == "INT" else "a number"
        shown = f"{v:.6g}" if real and isinstance(v, float) else repr(v)
        raise InputError(f"{where}: {name} = {shown} is {how} a lidar object holds; accepted: "
                         f"{kind} from {prop.hard_min:.6g} to {prop.hard_max:.6g} (the "
                         f"panel's {prop.name!r})")


def lidar_params(lidar) -> LidarParams:
    p = lidar.apcg_lidar
    check_lidar_values(lidar, {k: getattr(p, k) for k in LIDAR_VALUES},
                       f"lidar {lidar.name!r}")
    # the UI stores float32; round to what a person types so 0.004 deg stays 0.004 deg
    return LidarParams.from_degrees(round(p.r_alpha_deg, 7), round(p.r_beta_deg, 7),
                                    round(p.range_resolution_m, 7), int(p.width),
                                    int(p.height))


@leaves_nothing_on_error
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


def _mesh_arrays(ev):
    """(vertices float32 (V, 3), triangles int32 (F, 3)) of an evaluated object's mesh."""
    me = ev.to_mesh()
    try:
        me.calc_loop_triangles()
        verts = np.zeros(3 * len(me.vertices), np.float32)
        me.vertices.foreach_get("co", verts)
        tris = np.zeros(3 * len(me.loop_triangles), np.int32)
        me.loop_triangles.foreach_get("vertices", tris)
    finally:
        ev.to_mesh_clear()
    return verts.reshape(-1, 3), tris.reshape(-1, 3)


# what an instance can be and still have a surface (blender_import.py's SURFACE_TYPES)
_SURFACE_TYPES = {"MESH", "CURVE", "SURFACE", "META", "FONT"}


def _may_instance(obj) -> bool:
    """Whether an object can make instances (Geometry Nodes, particles, instancing by its
    vertices or faces): only then are the depsgraph's instances looked through."""
    return (getattr(obj, "instance_type", "NONE") not in ("NONE", "COLLECTION")
            or any(m.type in ("NODES", "PARTICLE_SYSTEM") for m in obj.modifiers))


def triangles_of(obj, depsgraph=None):
    """(vertices float64 (V, 3), faces int (F, 3)) of an object's evaluated geometry, local
    frame: its mesh and the instances it makes (Geometry Nodes' Instance on Points,
    particles...), as Blender draws them and as `apcg catalog add x.blend` takes them."""
    if not isinstance(obj, bpy.types.Object) or obj.type != "MESH":
        what = f"a {obj.type.lower()}" if isinstance(obj, bpy.types.Object) else "not an object"
        raise InputError(f"{named(obj)} is {what}, not a mesh object: it has no surface")
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(depsgraph)
    verts, tris = _mesh_arrays(ev)
    parts = [(verts.astype(np.float64), tris)]
    if _may_instance(obj):
        to_local = np.linalg.inv(_numpy_matrix(ev.matrix_world))
        for inst in depsgraph.object_instances:
            if not (inst.is_instance and inst.parent is not None
                    and inst.parent.original == obj.original
                    and inst.object.type in _SURFACE_TYPES):
                continue
            v, f = _mesh_arrays(inst.object)
            if not len(f):
                continue
            m = to_local @ _numpy_matrix(inst.matrix_world)
            if np.linalg.det(m[:3, :3]) < 0:  # a mirrored instance: keep faces outward
                f = f[:, ::-1]
            parts.append((v.astype(np.float64) @ m[:3, :3].T + m[:3, 3], f))
    if len(parts) == 1:
        return parts[0]
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    return (np.concatenate([v for v, _ in parts]),
            np.concatenate([f + o for (_, f), o in zip(parts, offsets, strict=True)]))


@dataclass
class _Mesh(Mesh):
    """A target's body mesh and its key for the simulator's caches: the object itself and a
    digest of its mesh's bytes, so a swapped or edited mesh, or another object of the same
    name (a linked library's), is never answered from another's caster."""
    key: tuple = ()


def checked_surface(label: str, vertices, faces, flat_ok: bool = True) -> Mesh:
    """The mesh as the catalog importer takes it (finite coordinates, some area; ``flat_ok``
    False: not flat either), without its zero-area triangles; else its InputError, naming
    ``label``."""
    from apcg_core.catalog.importer import check_not_flat, drop_degenerate
    if len(faces) == 0:
        raise InputError(f"{label} has no faces: a lidar would see nothing of it")
    mesh, _ = drop_degenerate(Mesh(vertices, faces), label)
    if not flat_ok:
        check_not_flat(mesh, label)
    return mesh


def body_mesh(obj, depsgraph=None) -> _Mesh:
    """A target's evaluated mesh in its body frame, as Blender shows it, checked as the
    catalog importer checks a model's."""
    v, f = triangles_of(obj, depsgraph)
    return checked_body_mesh(obj, v, f)


def mesh_key(obj, vertices, faces) -> tuple:
    """The simulator's cache key of a target's mesh: the object, and a digest of the mesh."""
    import hashlib
    digest = hashlib.blake2b(vertices.tobytes() + faces.tobytes(), digest_size=16).hexdigest()
    identity = getattr(obj, "session_uid", None) or obj.as_pointer()  # session_uid: 2.91+
    return ("blender-object", identity, digest)


def checked_body_mesh(obj, vertices, faces, key=None) -> _Mesh:
    """:func:`body_mesh` of the arrays :func:`triangles_of` gave (``key``: their mesh_key,
    when known)."""
    checked_surface(f"target {obj.name!r}", vertices, faces)
    return _Mesh(vertices, faces, key or mesh_key(obj, vertices, faces))


def pose_from_degrees(range_m, elevation_deg, pitch_deg=0.0, yaw_deg=0.0, roll_deg=0.0,
                      azimuth_deg=0.0) -> list[float]:
    """The pose in POSE_NAMES' order (m, rad), checked by the command line's rules
    (apcg_core.options: the same names, in degrees) and physically
    (apcg_core.condition.Condition), before anything is made of it."""
    from apcg_core.condition import Condition
    from apcg_core.options import check_values
    given = dict(zip(POSE_NAMES, (range_m, elevation_deg, pitch_deg, yaw_deg, roll_deg,
                                  azimuth_deg), strict=True))
    for name, v in given.items():
        if v is None:
            raise InputError(f"{name} must be a number, got None")
    check_values(**{k if k == "range_m" else f"{k}_deg": v for k, v in given.items()})
    vals = [float(range_m), *(math.radians(float(v)) for v in list(given.values())[1:])]
    Condition(0, *vals[:5])
    return vals


def set_pose(obj, range_m, elevation, pitch=0.0, yaw=0.0, roll=0.0, azimuth=0.0) -> None:
    """Place a target relative to its lidar (metres, radians; the angles in the project's one
    order, POSE_NAMES); keeps the exact doubles. A target under other objects (an Empty below
    the lidar) is placed through them."""
    lidar = lidar_of(obj)
    if not isinstance(obj, bpy.types.Object) or is_lidar(obj) or lidar is None:
        raise InputError(f"{named(obj)} is not a target of an APCG lidar: a pose places an "
                         "object parented to a lidar (apcg.add_aircraft, apcg.make_target)")
    vals = pose_from_degrees(range_m, *(_degrees(v) for v in (elevation, pitch, yaw, roll,
                                                               azimuth)))
    m = target_matrix_lidar_local(*vals)
    if obj.type == "MESH":
        check_clear_of_lidar(obj, vals, body_mesh(obj).vertices)
    obj[POSE_KEY] = dict(zip(POSE_NAMES, vals, strict=True))
    if obj.parent == lidar and obj.parent_type == "OBJECT":
        obj.matrix_parent_inverse.identity()
        obj.matrix_basis = _blender_matrix(m)
    else:  # through the objects between: Blender solves for the basis from the world matrix
        bpy.context.evaluated_depsgraph_get()  # their matrices current
        obj.matrix_world = lidar.matrix_world @ _blender_matrix(m)


def _blender_matrix(m) -> Matrix:
    return Matrix([list(row) for row in m])  # rows (a bare list means columns)


def _numpy_matrix(m) -> np.ndarray:
    return np.array([list(row) for row in m], dtype=np.float64)


def _plain_child(obj, lidar) -> bool:
    """Whether the target's matrix_basis alone places it in its lidar's frame (a target of
    no lidar: in the world's)."""
    return (obj.parent == lidar and (lidar is None or obj.parent_type == "OBJECT")
            and np.array_equal(_numpy_matrix(obj.matrix_parent_inverse), np.eye(4))
            and not any(not c.mute for c in obj.constraints))


AS_DRAWN = "as drawn"  # placement's depsgraph for a panel: the matrices the redraw left


def placement(obj, lidar=None, depsgraph=None) -> np.ndarray:
    """The target's 4 x 4 matrix in ``lidar``'s frame (default: its own lidar's; a target of
    no lidar: the world's), float64: the one placement that poses, scans, animations and the
    panel read. A plain child of its lidar is placed by its matrix_basis (exact: a stored pose
    keeps its doubles at 18 km); any other (constraints, a parent inverse, objects between) by
    the evaluated world matrices, made current first (``depsgraph``: the one to read, as a
    depsgraph handler has; None: the context's, evaluated now; AS_DRAWN: the objects' own
    matrix_world, what a draw may read without evaluating the scene)."""
    lidar = lidar_of(obj) if lidar is None else lidar
    if _plain_child(obj, lidar):
        return _numpy_matrix(obj.matrix_basis)
    if depsgraph is AS_DRAWN:
        lw, tw = (lidar.matrix_world if lidar else None), obj.matrix_world
    else:
        depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
        lw = lidar.evaluated_get(depsgraph).matrix_world if lidar else None
        tw = obj.evaluated_get(depsgraph).matrix_world
    tw = _numpy_matrix(tw)
    try:
        return tw if lw is None else np.linalg.solve(_numpy_matrix(lw), tw)
    except np.linalg.LinAlgError:
        raise InputError(f"lidar {lidar.name!r} has a zero scale: no frame to place target "
                         f"{obj.name!r} in; set its scale to 1") from None


def stored_pose(obj) -> dict:
    """The target's stored pose (POSE_NAMES -> finite float, m and rad); a damaged record
    (a name missing, not a number, the legacy list's length) is an InputError naming it."""
    stored = obj.get(POSE_KEY)
    try:
        if hasattr(stored, "to_dict"):
            values = [stored[k] for k in POSE_NAMES]
            names = POSE_NAMES
        elif hasattr(stored, "to_list") and len(stored) == len(_LEGACY_POSE_ORDER):
            values, names = stored.to_list(), _LEGACY_POSE_ORDER
        else:
            raise TypeError
    except (KeyError, TypeError):
        values = None
    if values is None or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                 and math.isfinite(v) for v in values):
        raise InputError(
            f"target {obj.name!r}: its {POSE_KEY} property is damaged ({_short(stored)}); "
            f"accepted: a record of {', '.join(POSE_NAMES)} as finite numbers (m, rad). "
            "Set the pose again (the panel's fields, or apcg.set_pose)")
    pose = dict(zip(names, map(float, values), strict=True))
    return {k: pose[k] for k in POSE_NAMES}


def _short(value) -> str:
    value = value.to_dict() if hasattr(value, "to_dict") else (
        value.to_list() if hasattr(value, "to_list") else value)
    text = repr(value)
    return text if len(text) <= 120 else text[:117] + "..."


def _differs(pose: dict, m: np.ndarray) -> bool:
    """Whether the matrix ``m`` (in the lidar's frame) no longer agrees with ``pose``."""
    p = [pose[k] for k in POSE_NAMES]
    want = target_matrix_lidar_local(*p)
    tol = _MOVED_TOL_M + _MOVED_TOL_REL * p[0]
    return bool(np.abs(m[:3, 3] - want[:3, 3]).max() > tol
                or np.abs(m[:3, :3] - want[:3, :3]).max() > 1e-5)


def pose_moved(obj, depsgraph=None) -> bool:
    """True when the object's placement no longer agrees with its stored pose (or that record
    is damaged: the placement is then the pose)."""
    try:
        pose = stored_pose(obj)
    except InputError:
        return True
    return _differs(pose, placement(obj, depsgraph=depsgraph))


def pose_of(obj, lidar=None, depsgraph=None) -> dict:
    """The target's pose in ``lidar``'s frame (default: its own lidar's): a dict of
    POSE_NAMES (m and rad). The stored doubles while the placement agrees with them; else
    (moved, or a damaged record) the pose of the placement."""
    require_target(obj, lidar=False)
    m = placement(obj, lidar, depsgraph)
    check_unit_scale(obj.name, m[:3, :3])
    owner = lidar if lidar is not None else lidar_of(obj)
    if owner is not None:
        check_lidar_scale(owner, depsgraph)
    if lidar is None or lidar == lidar_of(obj):
        try:
            pose = stored_pose(obj)
        except InputError:  # recovered from the matrix, which is what Blender shows
            pose = None
        if pose is not None and not _differs(pose, m):
            return pose
    try:
        return pose_from_lidar_local(m)
    except ValueError as exc:  # on the lidar: no range or direction
        raise InputError(f"{exc}: move target {obj.name!r} away from its lidar") from None


def panel_pose(obj) -> dict | None:
    """The pose the panel shows, never raising (it draws every redraw): the pose, else the
    stored one (a target Scan would refuse: scaled, on its lidar), else None (nothing
    readable: the fields show 0; Scan names the problem)."""
    try:
        return pose_of(obj, depsgraph=AS_DRAWN)
    except InputError:
        try:
            return stored_pose(obj)
        except InputError:
            return None


# A target's size is its mesh's (its type's, or the mesh it was made from): the float32 matrix
# of an unscaled object keeps its scale within ~1e-7 of 1.
_SCALE_TOL = 1e-4


def check_target_scale(obj) -> None:
    """Refuse a target whose scale in its lidar's frame is not 1: the simulator and the
    models cast its mesh as it is, so a scaled target would not be what Blender shows."""
    check_unit_scale(obj.name, placement(obj)[:3, :3])


def check_unit_scale(name: str, m3) -> None:
    """Refuse target ``name`` when its matrix's 3 x 3 part ``m3`` (in its lidar's frame)
    scales or mirrors it."""
    m3 = np.asarray(m3, dtype=np.float64)
    scale = np.linalg.norm(m3, axis=0)
    det = float(np.linalg.det(m3))
    if not np.all(np.isfinite(scale)) or np.abs(scale - 1.0).max() > _SCALE_TOL or det < 0:
        raise InputError(
            f"target {name!r} has scale ({', '.join(f'{v:.6g}' for v in scale)})"
            f"{', mirrored' if det < 0 else ''}: a target is scanned at its mesh's own size, "
            "so its scale must be 1. Set its scale to 1; for another size, scale the mesh "
            "object it was made from and make the target again (apcg.make_target)")


def check_lidar_scale(lidar, depsgraph=None) -> None:
    """Refuse a lidar whose world matrix scales or mirrors (its own scale, or a parent's):
    Blender draws its targets scaled by it, but a scan casts them at their mesh's own size
    from their pose, so the scan would not be what Blender shows."""
    if depsgraph is AS_DRAWN:
        m = lidar.matrix_world
    else:
        m = lidar.evaluated_get(depsgraph or bpy.context.evaluated_depsgraph_get()).matrix_world
    m3 = _numpy_matrix(m)[:3, :3]
    scale = np.linalg.norm(m3, axis=0)
    det = float(np.linalg.det(m3))
    if np.all(np.isfinite(scale)) and np.abs(scale - 1.0).max() <= _SCALE_TOL and det > 0:
        return
    own = np.asarray(lidar.scale, np.float64)
    whose = ("its own" if np.abs(np.abs(own) - 1.0).max() > _SCALE_TOL or (own < 0).any()
             else "its parents'")
    raise InputError(
        f"lidar {lidar.name!r} has scale ({', '.join(f'{v:.6g}' for v in scale)})"
        f"{', mirrored' if det < 0 else ''} in the world ({whose}): Blender draws its targets "
        "scaled by it, but a scan casts them at their mesh's own size, so a lidar's scale must "
        "be 1. Set its scale to 1, or apply it (Object > Apply > Scale), and so for its parents")


def check_clear_of_lidar(obj, pose, vertices) -> None:
    """Refuse a pose (POSE_NAMES' order, or a dict of them) that puts the lidar inside the
    target's bounding sphere (no ray could start outside it): the simulator's own check,
    here naming the target, before it is placed or scanned."""
    from dataset_builder.rays import bounding_radius, check_conditions
    p = [pose[k] for k in POSE_NAMES] if isinstance(pose, dict) else list(pose)
    try:
        check_conditions([[0.0, *p[:5]]], bounding_radius(vertices) if len(vertices) else 0.0)
    except InputError as exc:
        why = str(exc).removeprefix("condition 0: ")
        raise InputError(f"target {obj.name!r}: {why}") from None


def sync_pose(obj, depsgraph=None) -> bool:
    """Store the pose of a moved target as its doubles; True if it had moved."""
    if not (is_target(obj) and pose_moved(obj, depsgraph)):
        return False
    try:
        pose = pose_of(obj, depsgraph=depsgraph)
    except InputError:  # scaled, or on the lidar: it keeps its last pose, and a scan names why
        return False
    obj[POSE_KEY] = pose
    return True


def simulator_row(obj, mesh=None) -> np.ndarray:
    """The target's pose as the simulator's one-row table [0, r0, beta0, pitch, yaw, roll]
    (m, rad), checked clear of the lidar against ``mesh`` (default: its body mesh). The
    simulator is handed the target's own mesh, so the type column is unused and left 0; a type
    crosses to a model by its name (TYPE_KEY), never by a code."""
    p = pose_of(obj)
    check_clear_of_lidar(obj, p, (mesh or body_mesh(obj)).vertices)
    return np.array([[0.0, p["range_m"], p["elevation"], p["pitch"], p["yaw"], p["roll"]]])


def depth_length_of(obj, default=None):
    """The target's depth length (LENGTH_KEY, m; ``default`` where it has none): a finite
    number > 0, or an InputError naming the target and the property."""
    if LENGTH_KEY not in obj:
        return default
    v = obj[LENGTH_KEY]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise InputError(f"target {obj.name!r}: its {LENGTH_KEY} property is {_short(v)}; "
                         "accepted: a finite length in metres > 0 (make the target again, or "
                         "set the property)")
    return float(v)


@leaves_nothing_on_error
def add_aircraft(lidar, type_name: str, range_m: float, elevation_deg: float,
                 pitch_deg: float = 0.0, yaw_deg: float = 0.0, roll_deg: float = 0.0,
                 azimuth_deg: float = 0.0, catalog=None, name: str | None = None):
    """A catalog type (by name or index) as a target of ``lidar`` at the given pose."""
    require_lidar(lidar)
    # every check before anything is made: a refusal leaves the scene as it was
    pose = pose_from_degrees(range_m, elevation_deg, pitch_deg, yaw_deg, roll_deg, azimuth_deg)
    catalog = catalog or default_catalog()
    t = catalog.get(type_name)
    mesh = catalog.mesh(t)
    me = mesh_from_arrays(t.name, mesh.vertices, mesh.faces)
    obj = bpy.data.objects.new(name or t.name, me)
    obj[TYPE_KEY] = t.name
    obj[LENGTH_KEY] = float(catalog.depth_length_m(t))
    _link_like(obj, lidar)
    obj.parent = lidar
    set_pose(obj, *pose)
    return obj


def _degrees(radians):
    """An angle given in radians, in degrees for :func:`pose_from_degrees`; what is not a
    number is passed on as it is, to be refused by its own value."""
    if isinstance(radians, (bool, str)):
        return radians
    try:
        return math.degrees(float(radians))
    except (TypeError, ValueError, OverflowError):
        return radians


def world_mesh(obj, depsgraph=None) -> Mesh:
    """An object's evaluated mesh (modifiers applied, instances taken) with its world rotation
    and scale baked in (its size and orientation as placed in the scene), in metres: the
    scene's unit scale applied as `apcg catalog add x.blend` applies it (1 Blender unit is
    ``unit_settings.scale_length`` m, unless the unit system is None); its location is left
    out."""
    from apcg_core.catalog.blender_import import _blend_scale
    if not isinstance(obj, bpy.types.Object) or obj.type != "MESH":
        what = f"a {obj.type}" if isinstance(obj, bpy.types.Object) else "not an object"
        raise InputError(f"{named(obj)} is {what}, not a mesh object")
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    v, f = triangles_of(obj, depsgraph)
    checked_surface(repr(obj.name), v, f, flat_ok=False)  # what `apcg catalog add` takes
    m = obj.evaluated_get(depsgraph).matrix_world
    # the scene's unit, by the importer's own rule (it reads the scene of a .blend)
    unit = _blend_scale(".blend")
    rot_scale = unit * np.array([list(row)[:3] for row in list(m)[:3]], dtype=np.float64)
    if abs(np.linalg.det(rot_scale)) < 1e-30:
        raise InputError(f"{obj.name!r} has a zero scale: it has no size")
    return Mesh(v, f).transformed(rot_scale)  # faces flip with a mirroring (negative) scale


def guess_axes(mesh: Mesh):
    """The axes a mesh's shape suggests: apcg_core.catalog.checks.guess_axes, an AxesGuess of
    forward, up, why, confident (it runs without scipy too, as in Blender's own Python)."""
    from apcg_core.catalog.checks import guess_axes as core_guess
    return core_guess(mesh)


def _axes_for(mesh: Mesh, forward: str | None, up: str | None) -> dict:
    """Forward and up (file axes of ``mesh``), stated where given, else guessed."""
    from apcg_core.catalog.importer import AXES

    def axis(a):
        if a is not None and str(a).upper() not in AXES:
            raise InputError(f"axis {a!r} unknown; accepted: {', '.join(AXIS_NAMES)}")
        return None if a is None else str(a).upper()

    forward, up = axis(forward), axis(up)
    g = guess_axes(mesh)
    if forward is not None and up is not None:
        # stated axes that a confident guess contradicts: one line naming the fix
        from apcg_core.catalog.checks import axes_warning
        warning = axes_warning(g, forward, up, f"stated: forward {forward}, up {up}",
                               option=lambda k, v: f"{k.capitalize()} {v}")
        out = {"forward": forward, "up": up, "how": "stated", "why": "", "confident": True}
        if warning:
            out["warning"] = (warning.replace("(check with a preview)", "")
                              .rstrip() + ", or tick Guess axes")
        return out
    if forward is None and up is None:
        return {"forward": g.forward, "up": g.up, "how": "guessed", "why": g.why,
                "confident": bool(g.confident)}
    if up is None:  # forward stated
        up = g.up if g.up.lstrip("-") != forward.lstrip("-") else (
            "Z" if forward.lstrip("-") != "Z" else "Y")
        return {"forward": forward, "up": up, "how": "forward stated, up guessed",
                "why": g.why, "confident": bool(g.confident)}
    forward = g.forward if g.forward.lstrip("-") != up.lstrip("-") else (
        "X" if up.lstrip("-") != "X" else "Y")
    return {"forward": forward, "up": up, "how": "up stated, forward guessed", "why": g.why,
            "confident": bool(g.confident)}


def body_frame(mesh: Mesh, forward: str, up: str) -> tuple[Mesh, str]:
    """``mesh`` re-expressed in the body frame (x nose, y left wing, z up) from its
    ``forward`` / ``up`` axes, centred as the importer centres (SPEC section 2): at the volume
    centroid when closed, else at the bounding-box centre. Returns (mesh, how centred)."""
    from apcg_core.catalog.importer import axis_matrix
    body = mesh.transformed(axis_matrix(forward, up))
    rep = body.report()
    if rep.watertight and abs(rep.volume) > 0:
        body = body.outward()
        origin, how = body.centroid, "volume centroid"
    else:
        origin, how = body.bounds.mean(axis=0), "bounding-box centre"
    return body.transformed(offset=-origin), how


def default_range_m(extents) -> float:
    """A first range for a made target: the middle of Table 1's band its size suggests, or
    ten times its largest extent for an object too big for that band (the lidar stays well
    outside its bounding sphere)."""
    band = 300.0 if float(max(extents[0], extents[1])) < 5.0 else 4500.0
    return max(band, 10.0 * float(max(extents)))


@leaves_nothing_on_error
def make_target(lidar, obj, range_m: float | None = None, elevation_deg: float = 3.4,
                pitch_deg: float = 0.0, yaw_deg: float = 0.0, roll_deg: float = 0.0,
                azimuth_deg: float = 0.0, depth_length_m: float | None = None, *,
                forward: str | None = None, up: str | None = None,
                type_name: str | None = None, name: str | None = None, catalog=None,
                depsgraph=None):
    """A target of ``lidar`` made from any mesh object, which itself is left as it is.

    The target's body mesh is the object's evaluated mesh (modifiers applied) at its world size
    and orientation (scale and rotation baked in), re-expressed in the body frame from its
    ``forward`` / ``up`` axes ("X", "-X", "Y", "-Y", "Z", "-Z", in the object's world
    orientation; each one not given is guessed from the shape) and centred at its centre of
    mass. The new object "<name> (target)" goes into the object's collection, parented to
    ``lidar`` (``None``: the scene's first lidar, or a new one) at the pose (``range_m`` None:
    4500 m, 300 m for an object under 5 m). Its type is ``type_name`` (default: the object's
    name); a catalog name lets Generate use a model that knows that type. How the axes were
    found is kept under AXES_KEY.

    The object itself stays where it is and stands for the target from then on: it hides
    nothing from any scan (of this target or of others), since the aircraft is in the scene as
    its target already, so a new lidar added at the origin may sit inside it (SOURCE_KEY)."""
    if not isinstance(obj, bpy.types.Object) or obj.type != "MESH":
        raise InputError(f"{named(obj)} is not a mesh object: select the "
                         "mesh of your model")
    if is_target(obj) or obj.get("apcg_cloud") is not None:
        raise InputError(f"{obj.name!r} already is an APCG target or cloud: select the mesh "
                         "object of your model")
    if lidar is not None:
        require_lidar(lidar)
    # every check before anything is made: a refusal leaves the scene as it was
    pose_from_degrees(4500.0 if range_m is None else range_m, elevation_deg, pitch_deg,
                      yaw_deg, roll_deg, azimuth_deg)
    if depth_length_m is not None:
        from apcg_core.options import check_values
        check_values(length_m=depth_length_m)
    world = world_mesh(obj, depsgraph)
    axes = _axes_for(world, forward, up)
    body, centre = body_frame(world, axes["forward"], axes["up"])
    axes["centre"] = centre
    axes["extents_m"] = [float(e) for e in body.extents]  # length, span, height
    catalog = catalog or default_catalog()
    type_name = (type_name or "").strip() or obj.name
    known = {n.lower(): n for n in catalog.names()}
    length = float(body.extents[0])
    if type_name.lower() in known:
        type_name = known[type_name.lower()]
        length = float(catalog.depth_length_m(type_name))
    if range_m is None:
        range_m = default_range_m(body.extents)
    if lidar is None:
        lidar = next((o for o in bpy.context.scene.objects if is_lidar(o)), None) or add_lidar()
    me = mesh_from_arrays(name or f"{obj.name} (target)", body.vertices, body.faces)
    for mat in getattr(obj.data, "materials", ()):
        me.materials.append(mat)
    target = bpy.data.objects.new(name or f"{obj.name} (target)", me)
    target[TYPE_KEY] = type_name
    target[LENGTH_KEY] = float(depth_length_m or length)
    target[AXES_KEY] = axes
    target[SOURCE_KEY] = obj
    cols = list(obj.users_collection) or [bpy.context.scene.collection]
    cols[0].objects.link(target)
    target.parent = lidar
    set_pose(target, range_m, *(math.radians(v) for v in (elevation_deg, pitch_deg, yaw_deg,
                                                           roll_deg, azimuth_deg)))
    return target


def axes_label(obj) -> str:
    """'forward -Y, up Z (guessed)' for a made target; '' for others."""
    axes = obj.get(AXES_KEY) if isinstance(obj, bpy.types.Object) else None
    if not axes:
        return ""
    low = "" if axes.get("confident", True) else ", unsure"
    return f"forward {axes['forward']}, up {axes['up']} ({axes['how']}{low})"


def source_of(obj):
    """The scene object a made target was made from (None for catalog types)."""
    src = obj.get(SOURCE_KEY) if isinstance(obj, bpy.types.Object) else None
    return src if isinstance(src, bpy.types.Object) else None


def targets_of(lidar, selected_only: bool = False) -> list:
    """The lidar's targets: every target below it (through Empties, rigs...) whose nearest
    lidar it is (a lidar below it has its own); Scan, Generate and Scan Animation all take
    these. Objects that carry a pose but are no mesh are not targets."""
    lidar = require_lidar(lidar)
    kids = [o for o in lidar.children_recursive if is_target(o) and lidar_of(o) == lidar]
    if selected_only:
        kids = [o for o in kids if o.select_get()]
    return kids


def _link_like(obj, other) -> None:
    cols = list(other.users_collection) or [bpy.context.scene.collection]
    cols[0].objects.link(obj)
