"""Point clouds as Blender objects: vertex-only meshes with per-point attributes, shown as
points through one shared Geometry Nodes group with a range-coloured material (renders in
Cycles and EEVEE).

A cloud object is parented to its lidar. Its origin sits at the cloud's centre and its vertices
are relative to it, so float32 vertex coordinates keep sub-millimetre detail at 18 km; the
origin, r0 and the frame are kept as double-precision custom properties, and export rebuilds
the observation-frame cloud in float64 from them.
"""

from __future__ import annotations

import json
import math
import re

import bpy
import numpy as np

from apcg_core.cloud import PHOTON_FIELDS, PointCloud
from apcg_core.errors import InputError
from apcg_core.frames import lidar_local_to_observation, observation_to_lidar_local
from apcg_core.io.clouds import read_cloud_attributes, write_cloud

from .objects import leaves_nothing_on_error, named

CLOUD_KEY = "apcg_cloud"  # JSON: source, r0, beta0, azimuth, origin (lidar-local, m), meta
GROUP_NAME = "APCG Points"
MATERIAL_NAME = "APCG Range"
PHOTON_GROUP_NAME = "APCG Photon Points"
PHOTON_MATERIAL_NAME = "APCG Signal / Noise"
SOURCES = {"scan": 0, "generated": 1, "imported": 2}


def is_cloud(obj) -> bool:
    return isinstance(obj, bpy.types.Object) and obj.get(CLOUD_KEY) is not None


# what a cloud object's record must hold for the cloud to be read back
_INFO_KEYS = ("source", "origin", "azimuth", "r0")
_AGAIN = "import or make the cloud again"


def _damaged(obj, what: str) -> InputError:
    return InputError(f"{obj.name!r}: {what}; {_AGAIN}")


def cloud_info(obj) -> dict:
    """A cloud object's record (its ``apcg_cloud`` property), every field read back checked;
    a damaged one is named."""
    try:
        info = json.loads(obj[CLOUD_KEY])
    except (TypeError, ValueError) as exc:
        raise _damaged(obj, f"its {CLOUD_KEY} property is not the JSON record an APCG cloud "
                            f"carries ({exc})") from exc
    missing = [k for k in _INFO_KEYS if not isinstance(info, dict) or k not in info]
    if missing:
        raise _damaged(obj, f"its {CLOUD_KEY} record lacks {', '.join(missing)}")

    def real(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    origin = info["origin"]
    fields = info.get("photon_fields", [])
    bad = [k for k, ok in (
        ("origin", isinstance(origin, list) and len(origin) == 3 and all(map(real, origin))),
        ("azimuth", real(info["azimuth"])),
        ("r0", real(info["r0"])),
        ("source", info["source"] in SOURCES),
        ("meta", isinstance(info.get("meta", {}), dict)),
        ("has_sample", isinstance(info.get("has_sample", False), bool)),
        ("photon_fields", isinstance(fields, list) and set(fields) <= set(PHOTON_FIELDS)))
        if not ok]
    if bad:
        raise _damaged(obj, f"its {CLOUD_KEY} record's {', '.join(bad)} "
                            f"{'is' if len(bad) == 1 else 'are'} damaged (origin: 3 numbers; "
                            f"azimuth, r0: numbers; source: one of {', '.join(SOURCES)}; "
                            "meta: a JSON object; has_sample: true or false; photon_fields: "
                            f"some of {', '.join(PHOTON_FIELDS)})")
    return info


# --- the shared display -------------------------------------------------------------------------
def _socket(sockets, *names: str):
    """The first enabled socket called one of ``names`` (Blender renames some: Fac, Factor)."""
    for name in names:
        for s in sockets:
            if s.name == name and getattr(s, "enabled", True):
                return s
    raise RuntimeError(f"node has no socket {names}: {[s.name for s in sockets]}")


def _group_input(tree, name: str, socket_type: str, default=None) -> str:
    """Adds a group input; returns its identifier (what a modifier is keyed by)."""
    if hasattr(tree, "interface"):  # Blender 4.0+
        sock = tree.interface.new_socket(name=name, in_out="INPUT", socket_type=socket_type)
    else:
        sock = tree.inputs.new(socket_type, name)
    if default is not None:
        sock.default_value = default
    return sock.identifier


def _group_output(tree, name: str, socket_type: str) -> None:
    if hasattr(tree, "interface"):
        tree.interface.new_socket(name=name, in_out="OUTPUT", socket_type=socket_type)
    else:
        tree.outputs.new(socket_type, name)


def range_material():
    """Emission coloured by the per-point ``range_norm`` attribute (near: yellow, far: blue)."""
    return _ramp_material(MATERIAL_NAME, "range_norm", (1.0, 0.85, 0.1, 1.0),
                          (0.05, 0.25, 1.0, 1.0), (1.0, 0.6, 0.1, 1.0))


def photon_material():
    """Emission coloured by a photon cloud's ``label`` (noise 0: red, signal 1: cyan)."""
    return _ramp_material(PHOTON_MATERIAL_NAME, "label", (1.0, 0.12, 0.05, 1.0),
                          (0.1, 0.9, 1.0, 1.0), (0.1, 0.9, 1.0, 1.0))


def _ramp_material(name: str, attribute: str, low, high, solid):
    mat = bpy.data.materials.get(name)
    if mat is not None:
        return mat
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None or bpy.app.version < (5, 0, 0):  # 5.0: always node-based
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    attr = nt.nodes.new("ShaderNodeAttribute")
    attr.attribute_type = "GEOMETRY"
    attr.attribute_name = attribute
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = low
    ramp.color_ramp.elements[1].color = high
    emit = nt.nodes.new("ShaderNodeEmission")
    _socket(emit.inputs, "Strength").default_value = 2.0
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(_socket(attr.outputs, "Fac", "Factor"),
                 _socket(ramp.inputs, "Fac", "Factor"))
    nt.links.new(_socket(ramp.outputs, "Color"), _socket(emit.inputs, "Color"))
    nt.links.new(_socket(emit.outputs, "Emission"), _socket(out.inputs, "Surface"))
    mat.diffuse_color = solid  # solid viewport colour
    return mat


def points_group(photons: bool = False):
    """The node group every cloud uses: Mesh to Points (radius) + Set Material (range colours;
    for a photon cloud, signal / noise colours)."""
    name = PHOTON_GROUP_NAME if photons else GROUP_NAME
    tree = bpy.data.node_groups.get(name)
    if tree is not None:
        return tree
    tree = bpy.data.node_groups.new(name, "GeometryNodeTree")
    _group_input(tree, "Geometry", "NodeSocketGeometry")
    _group_input(tree, "Radius", "NodeSocketFloat", 0.1)
    _group_output(tree, "Geometry", "NodeSocketGeometry")
    nodes, links = tree.nodes, tree.links
    gin, gout = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    to_points = nodes.new("GeometryNodeMeshToPoints")
    set_mat = nodes.new("GeometryNodeSetMaterial")
    material = photon_material() if photons else range_material()
    _socket(set_mat.inputs, "Material").default_value = material
    links.new(_socket(gin.outputs, "Geometry"), _socket(to_points.inputs, "Mesh"))
    links.new(_socket(gin.outputs, "Radius"), _socket(to_points.inputs, "Radius"))
    links.new(_socket(to_points.outputs, "Points"), _socket(set_mat.inputs, "Geometry"))
    links.new(_socket(set_mat.outputs, "Geometry"), _socket(gout.inputs, "Geometry"))
    return tree


def _radius_identifier(tree) -> str:
    if hasattr(tree, "interface"):
        return next(i.identifier for i in tree.interface.items_tree
                    if getattr(i, "in_out", None) == "INPUT" and i.name == "Radius")
    return tree.inputs["Radius"].identifier


def set_point_radius(obj, radius: float) -> None:
    """The displayed radius of a cloud object's points (metres)."""
    if not is_cloud(obj):
        raise InputError(f"{named(obj)} is not an APCG point cloud object")
    try:
        radius = float(radius)
    except (TypeError, ValueError):
        radius = math.nan
    if not (math.isfinite(radius) and radius > 0):
        raise InputError(f"radius must be a finite number of metres > 0, got {radius!r}")
    mod = obj.modifiers.get("APCG points")
    mod[_radius_identifier(mod.node_group)] = float(radius)
    obj.update_tag()


# --- cloud <-> object ---------------------------------------------------------------------------
def _add_attr(me, name: str, kind: str, values) -> None:
    attr = me.attributes.new(name, kind, "POINT")
    attr.data.foreach_set("value", np.ascontiguousarray(values).ravel())


@leaves_nothing_on_error
def cloud_object(cloud: PointCloud, name: str, lidar=None, source: str = "scan",
                 r0: float | None = None, beta0: float = 0.0, azimuth: float = 0.0,
                 meta: dict | None = None, radius: float | None = None, collection=None):
    """A vertex-only mesh object for ``cloud`` (observation frame of a target seen at
    ``azimuth``), parented to ``lidar`` when given, displayed as points."""
    if source not in SOURCES:
        raise InputError(f"source must be one of {sorted(SOURCES)}, got {source!r}")
    local = observation_to_lidar_local(cloud.xyz, azimuth)
    origin = local.mean(axis=0) if len(local) else np.zeros(3)
    rng = cloud.range_m
    r0 = float(np.median(rng)) if r0 is None and len(rng) else float(r0 or 0.0)
    _check_float32(name, local - origin, rng - r0)
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(local))
    me.vertices.foreach_set("co", (local - origin).astype(np.float32).ravel())
    lo, hi = (float(rng.min()), float(rng.max())) if len(rng) else (0.0, 1.0)
    _add_attr(me, "range", "FLOAT", rng.astype(np.float32))
    _add_attr(me, "delta_range", "FLOAT", (rng - r0).astype(np.float32))
    _add_attr(me, "range_norm", "FLOAT", ((rng - lo) / max(hi - lo, 1e-9)).astype(np.float32))
    _add_attr(me, "cell_w", "INT", cloud.cell_w.astype(np.int32))
    _add_attr(me, "cell_h", "INT", cloud.cell_h.astype(np.int32))
    sample = cloud.sample if cloud.sample is not None else np.zeros(len(local), np.int64)
    _add_attr(me, "sample", "INT", sample.astype(np.int32))
    _add_attr(me, "source", "INT", np.full(len(local), SOURCES[source], np.int32))
    for field in cloud.photon_fields:  # a photon cloud: label (1 signal, 0 noise), count...
        _add_attr(me, field, "INT", getattr(cloud, field).astype(np.int32))
    photons = cloud.label is not None
    me.update()
    obj = bpy.data.objects.new(name, me)
    obj[CLOUD_KEY] = json.dumps({"source": source, "r0": r0, "beta0": float(beta0),
                                 "azimuth": float(azimuth), "origin": origin.tolist(),
                                 "has_sample": cloud.sample is not None, "meta": meta or {},
                                 "photon_fields": cloud.photon_fields})
    (collection or (lidar.users_collection[0] if lidar is not None and lidar.users_collection
                    else bpy.context.scene.collection)).objects.link(obj)
    if lidar is not None:
        obj.parent = lidar
        obj.matrix_parent_inverse.identity()
    obj.location = origin
    mod = obj.modifiers.new("APCG points", "NODES")
    mod.node_group = points_group(photons)
    if radius is None:  # about half a cell across at the cloud's range
        cell = math.radians((meta or {}).get("lidar", {}).get("r_alpha_deg", 0.004))
        radius = max(0.45 * cell * max(r0, 1.0), 0.005)
    set_point_radius(obj, radius)
    obj.data.materials.append(photon_material() if photons else range_material())
    bpy.context.view_layer.update()  # so matrix_world is right for the caller
    return obj


# the kind of each point attribute a cloud object's own values are kept in
_ATTR_KINDS = {np.float32: "FLOAT", np.int32: "INT"}


def _check_float32(name: str, offsets, deltas) -> None:
    """Refuse a cloud whose offsets from its origin (or ranges from r0) a float32 vertex or
    attribute cannot hold: they would become infinities."""
    big = np.finfo(np.float32).max
    for what, a in (("coordinates", offsets), ("ranges", deltas)):
        if len(a) and not np.abs(a).max() < big:
            raise InputError(f"{name!r}: its {what} spread over {float(np.abs(a).max()):.3g} m,"
                             f" more than Blender's float32 holds (accepted: under {big:.3g} m "
                             "from the cloud's centre)")


def _spacing_radius(xyz: np.ndarray) -> float:
    """Half the typical spacing of points on a surface (its two largest extents shared among
    the points): a radius for a cloud of no known lidar, wherever it lies (a georeferenced
    cloud's range from the origin says nothing of its cells)."""
    if len(xyz) < 2:
        return 0.05
    ext = np.sort(xyz.max(axis=0) - xyz.min(axis=0))[::-1]
    area = float(ext[0] * max(ext[1], ext[0] * 1e-3))
    return max(0.5 * math.sqrt(area / len(xyz)), 0.005)


def _get_attr(obj, name: str, dtype, n: int):
    """A cloud object's own point attribute ``name`` as ``dtype`` (None when it has none);
    one of another kind or domain (edited, or added by another tool) is named."""
    a = obj.data.attributes.get(name)
    if a is None:
        return None
    kind = _ATTR_KINDS[dtype]
    if a.data_type != kind or a.domain != "POINT" or len(a.data) != n:
        raise _damaged(obj, f"its point attribute {name!r} is {a.data_type} on the "
                            f"{a.domain} domain ({len(a.data)} values); a cloud's is {kind} on "
                            f"the POINT domain, one value per point ({n})")
    out = np.zeros(n, dtype)
    a.data.foreach_get("value", out)
    return out


def cloud_from_object(obj) -> tuple[PointCloud, dict]:
    """The observation-frame cloud (float64) of a cloud object, and its info."""
    if not is_cloud(obj) or obj.type != "MESH":
        raise InputError(f"{named(obj)} is not an APCG point cloud object")
    info = cloud_info(obj)
    me = obj.data
    n = len(me.vertices)
    co = np.zeros(3 * n, np.float32)
    me.vertices.foreach_get("co", co)
    local = co.reshape(-1, 3).astype(np.float64) + np.asarray(info["origin"])
    xyz = lidar_local_to_observation(local, info["azimuth"])
    delta = _get_attr(obj, "delta_range", np.float32, n)
    rng = (info["r0"] + delta.astype(np.float64)) if delta is not None else np.linalg.norm(
        xyz, axis=1)
    w = _get_attr(obj, "cell_w", np.int32, n)
    h = _get_attr(obj, "cell_h", np.int32, n)
    sample = _get_attr(obj, "sample", np.int32, n) if info.get("has_sample") else None
    zeros = np.zeros(n, np.int32)
    photon = {f: _get_attr(obj, f, np.int32, n) for f in info.get("photon_fields", [])}
    lost = [f for f, v in photon.items() if v is None]
    if lost:
        raise _damaged(obj, f"its record names the photon attributes {', '.join(lost)}, "
                            "which it has no longer")
    return PointCloud(xyz, rng, zeros if w is None else w, zeros if h is None else h,
                      sample, **photon), info


@leaves_nothing_on_error
def import_cloud(path, lidar=None, name: str | None = None):
    """A PLY / NPZ / LAS / LAZ cloud, written by apcg or another lidar tool, as an object. Every
    other per-point value of the file (intensity, classification, normals, extra bytes...)
    becomes a point attribute of the mesh, shown in the spreadsheet; red / green / blue also
    the colour attribute "Col". The attributes' names are kept in the info's "attributes"."""
    path = checked_path(path, "path", "a point cloud file (.ply, .npz, .las, .laz)")
    cloud, meta, attrs = read_cloud_attributes(path)
    # a photon cloud's own fields are its attributes already (cloud_object)
    attrs = {k: v for k, v in attrs.items() if k not in cloud.photon_fields}
    r0, beta0 = _pose_of_file(path, meta)
    # an APCG file's cells size its points; another tool's cloud, its own spacing
    radius = None if "r_alpha_deg" in (meta.get("lidar") or {}) else _spacing_radius(cloud.xyz)
    try:
        obj = cloud_object(cloud, name or path.stem, lidar=lidar, source="imported",
                           r0=r0, beta0=beta0, meta=meta, radius=radius)
    except InputError as exc:
        raise InputError(f"cannot import {path}: {exc}") from None
    info = cloud_info(obj)
    info["attributes"] = _add_file_attrs(obj.data, attrs)
    obj[CLOUD_KEY] = json.dumps(info)
    return obj


def checked_path(value, what: str, accepted: str):
    """``value`` as a Path when it names one (str, bytes or a path-like, not blank); else an
    InputError naming ``what`` and what is ``accepted``."""
    import os
    from pathlib import Path
    if isinstance(value, bytes):
        value = os.fsdecode(value)
    if not isinstance(value, (str, os.PathLike)) or not str(os.fspath(value)).strip():
        raise InputError(f"{what} = {value!r}: give {accepted}")
    return Path(value)


def _number(path, what: str, v, lo: float, hi: float) -> float:
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and lo < v < hi
    if not ok:
        raise InputError(f"{path}: its metadata's {what} = {v!r} is not a number in "
                         f"({lo:g}, {hi:g})")
    return float(v)


def _pose_of_file(path, meta) -> tuple:
    """(r0 or None, beta0) from a cloud file's metadata (an apcg file's condition), checked:
    the object is placed and its points sized from them."""
    if not isinstance(meta, dict):
        raise InputError(f"{path}: its metadata is not a JSON object (got {type(meta).__name__})")
    cond = meta.get("condition") or {}
    lidar = meta.get("lidar") or {}
    for what, v in (("condition", cond), ("lidar", lidar)):
        if not isinstance(v, dict):
            raise InputError(f"{path}: its metadata's {what} is not a JSON object")
    if "r_alpha_deg" in lidar:
        _number(path, "lidar.r_alpha_deg", lidar["r_alpha_deg"], 0.0, 180.0)
    r0 = cond.get("range_m")
    if r0 is not None:
        r0 = _number(path, "condition.range_m", r0, 0.0, 1e7)
    beta0 = 0.0
    if "elevation_deg" in cond:
        beta0 = math.radians(_number(path, "condition.elevation_deg", cond["elevation_deg"],
                                     -90.0, 90.0))
    return r0, beta0


def _new_attr(me, name: str, kind: str):
    """A new point attribute named like ``name``: Blender hides names starting with ".", refuses
    long ones and built-in ones (material_index...), so those get cleaned or a _1, _2 suffix."""
    base = re.sub(r"[^\w .-]", "_", name, flags=re.ASCII).lstrip(".")[:48] or "attribute"
    for i in range(1000):
        cand = f"{base}_{i}" if i else base
        if cand not in me.attributes:
            attr = me.attributes.new(cand, kind, "POINT")
            if attr is not None:
                return attr
    raise InputError(f"cannot add an attribute named like {name!r} to {me.name!r}")


def _add_file_attrs(me, attrs: dict) -> list[str]:
    """Blender's attributes are 32-bit: integers that fit stay INT, the rest become FLOAT."""
    names = []
    for name, a in attrs.items():
        fits = a.dtype.kind in "biu" and (a.size == 0 or (a.min() >= -2**31 and a.max() < 2**31))
        attr = _new_attr(me, name, "INT" if fits else "FLOAT")
        attr.data.foreach_set("value", a.astype(np.int32 if fits else np.float32))
        names.append(attr.name)
    if {"red", "green", "blue"} <= attrs.keys():
        rgb = np.stack([attrs[c] for c in ("red", "green", "blue")], 1).astype(np.float64)
        if attrs["red"].dtype.kind in "iu" and len(rgb):
            # LAS colours are 16-bit, but many tools store 8-bit values in them
            rgb /= 255.0 if rgb.max() <= 255 else 65535.0
        col = _new_attr(me, "Col", "FLOAT_COLOR")
        rgba = np.column_stack([rgb, np.ones(len(rgb))]).astype(np.float32)
        col.data.foreach_set("color_srgb", rgba.ravel())  # file colours are sRGB
        names.append(col.name)
    me.update()
    return names


def export_cloud(obj, path) -> str:
    """Write a cloud object to PLY / NPZ / LAS / LAZ (by extension), observation frame, float64.

    An imported cloud's file attributes (another tool's intensity, classification, colours...:
    the info's "attributes") are written too, as the format can carry them: PLY and NPZ as
    columns of their own names; LAS / LAZ into the point format's own dimension of that name
    (intensity, classification, red / green / blue...: point format 7 when there are colours)
    where the values fit it, else as extra bytes. One that a format cannot carry is said in one
    warning (``warnings.warn``, an :class:`ExportWarning`), never dropped silently."""
    cloud, info = cloud_from_object(obj)
    path = checked_path(path, "path", "a file path ending in .ply, .npz, .las or .laz")
    meta = dict(info.get("meta") or {})
    meta.update({"exported_from_blender": obj.name, "source": info["source"]})
    extras, lost = _file_attributes(obj, info, len(cloud))
    if not extras:
        out = write_cloud(path, cloud, meta)
    else:
        out = _write_with_attributes(path, cloud, meta, extras, lost)
    if lost:
        import warnings
        warnings.warn(f"{path.name}: {'; '.join(lost)}", ExportWarning, stacklevel=2)
    return str(out)


class ExportWarning(UserWarning):
    """A file attribute of the cloud that the exported format cannot carry (in one line)."""


def _file_attributes(obj, info, n: int) -> tuple[dict, list]:
    """The cloud object's file attributes (its info's "attributes", as imported) by name:
    Blender's INT as int32, FLOAT as float32. The colour attribute (made from red / green /
    blue, which go themselves) is not one. Returns (attributes, what cannot be taken, in
    words)."""
    out, lost = {}, []
    gone = []
    for name in info.get("attributes") or []:
        a = obj.data.attributes.get(name)
        if a is None:
            gone.append(name)
            continue
        if a.data_type == "FLOAT_COLOR" or a.data_type == "BYTE_COLOR":
            continue  # "Col": shown from red / green / blue
        kind = _ATTR_KINDS_BY_TYPE.get(a.data_type)
        if kind is None or a.domain != "POINT" or len(a.data) != n:
            lost.append(f"attribute {name!r} ({a.data_type} on the {a.domain} domain) is not "
                        "one number per point: not written")
            continue
        v = np.zeros(n, kind)
        a.data.foreach_get("value", v)
        out[name] = v
    if gone:
        lost.append(f"the attribute{'s' if len(gone) > 1 else ''} {', '.join(map(repr, gone))}"
                    f" of the imported file {'are' if len(gone) > 1 else 'is'} no longer on "
                    f"{obj.name!r}: not written")
    return out, lost


_ATTR_KINDS_BY_TYPE = {"FLOAT": np.float32, "INT": np.int32}


def _write_with_attributes(path, cloud: PointCloud, meta: dict, extras: dict,
                           lost: list):
    """write_cloud's file of ``cloud`` with ``extras`` added (see :func:`export_cloud`),
    written whole or not at all; what the format cannot carry is added to ``lost``."""
    import tempfile
    from pathlib import Path

    from apcg_core.io.atomic import refuse_directory
    from apcg_core.io.clouds import _fmt
    from apcg_core.io.dataset import write_atomic
    ext = _fmt(path)  # refused, naming the file, before any work
    refuse_directory(path)
    with tempfile.TemporaryDirectory(prefix="apcg-export-") as d:
        base = Path(d) / f"base{ext}"
        write_cloud(base, cloud, meta)
        own = {"xyz", "x", "y", "z", "meta", "range_m", "cell_w", "cell_h", "sample",
               *cloud.photon_fields}
        taken = {}
        for name, v in extras.items():
            if ext in (".ply", ".npz") and name in own:
                lost.append(f"attribute {name!r} has the name of one of the file's own "
                            "columns: not written")
            else:
                taken[name] = v
        if ext == ".npz":
            data = _npz_with(base, taken)
        elif ext == ".ply":
            data = _ply_with(base, taken, lost)
        else:
            data = _las_with(base, taken, lost, cloud, compress=ext == ".laz")
    write_atomic(path, data)
    return path


def _npz_with(base, extras: dict) -> bytes:
    import io
    with np.load(base, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update(extras)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


_PLY_OF = {"f8": "double", "f4": "float", "i4": "int", "u1": "uchar", "i1": "char",
           "i2": "short", "u2": "ushort", "u4": "uint"}


def _ply_with(base, extras: dict, lost: list) -> bytes:
    """The binary PLY ``base`` (write_cloud's) with a property per attribute (a PLY name has
    no spaces: they become "_")."""
    from apcg_core.io.clouds import ply_header_end
    data = base.read_bytes()
    end = ply_header_end(data)
    head = data[:end].decode()
    body = data[data.index(b"\n", end) + 1:]
    of_ply = {v: k for k, v in _PLY_OF.items()}
    props = [line.split()[1:] for line in head.splitlines() if line.startswith("property ")]
    dtype = [(n, "<" + of_ply[t]) for t, n in props]
    rec = np.frombuffer(body, dtype=dtype)
    names = {n for _, n in props}
    add = []
    for name, v in extras.items():
        ply = re.sub(r"\s", "_", name)
        if ply in names:
            lost.append(f"attribute {name!r} has the name of one of the file's own columns "
                        "in PLY: not written")
            continue
        names.add(ply)
        add.append((ply, v))
    out = np.empty(len(rec), dtype=dtype + [(n, "<" + v.dtype.str[1:]) for n, v in add])
    for n, _t in dtype:
        out[n] = rec[n]
    for n, v in add:
        out[n] = v
    lines = [f"property {_PLY_OF[v.dtype.str[1:]]} {n}" for n, v in add]
    return (head + "".join(line + "\n" for line in lines) + "end_header\n").encode() + \
        out.tobytes()


def _las_with(base, extras: dict, lost: list, cloud: PointCloud, compress: bool) -> bytes:
    """The LAS / LAZ ``base`` (write_cloud's, point format 6) with each attribute in the
    point format's own dimension of its name where its values fit it (colours: format 7),
    else as extra bytes of its own name (32 characters at most)."""
    import io

    import laspy
    las = laspy.read(base)
    if {"red", "green", "blue"} <= extras.keys():
        las = laspy.convert(las, point_format_id=8 if "nir" in extras else 7)
    fmt = las.point_format
    standard = {d.name: d for d in fmt.dimensions if d.is_standard}
    for name, v in extras.items():
        if name in ("X", "Y", "Z", "x", "y", "z") or name in ("range_m", "cell_w", "cell_h",
                                                              "sample", "count", "pulse"):
            lost.append(f"attribute {name!r} has the name of one of the file's own columns "
                        "in LAS: not written")
            continue
        if name == "classification" and cloud.label is not None:
            continue  # a photon cloud's classification is its label's (LAS_CLASS)
        dim = standard.get(name)
        if dim is not None:
            if _fits(v, dim):
                las[name] = v
                continue
            lost.append(f"attribute {name!r}: values from {v.min():g} to {v.max():g} do not "
                        f"fit LAS's {name} ({_range_of(dim)}): not written")
            continue
        if len(name.encode()) > 32 or not name.isascii():
            lost.append(f"attribute {name!r}: LAS names an extra dimension in 32 ASCII "
                        "characters at most: not written")
            continue
        las.add_extra_dim(laspy.ExtraBytesParams(name, v.dtype))
        las[name] = v
    buf = io.BytesIO()
    las.write(buf, do_compress=compress)
    return buf.getvalue()


def _dim_bounds(dim) -> tuple:
    if dim.kind.name == "FloatingPoint":
        return None
    if dim.kind.name == "BitField":
        return 0, 2 ** dim.num_bits - 1
    info = np.iinfo(dim.dtype)
    return int(info.min), int(info.max)


def _fits(v: np.ndarray, dim) -> bool:
    bounds = _dim_bounds(dim)
    if bounds is None:
        return True
    whole = v.dtype.kind in "iu" or bool(np.all(np.isfinite(v)) and np.all(v == np.round(v)))
    return whole and (not len(v) or (bounds[0] <= v.min() and v.max() <= bounds[1]))


def _range_of(dim) -> str:
    bounds = _dim_bounds(dim)
    return "any number" if bounds is None else f"whole numbers {bounds[0]}..{bounds[1]}"
