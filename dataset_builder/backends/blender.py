"""The ``blender`` backend: Blender's own ray casting, inside bpy (the PyPI module or a running
Blender, e.g. ``blender -b -P``).

``geometry-nodes`` (default) evaluates one Geometry Nodes Raycast over a vertex-only mesh with
one point per ray (attributes ``ray_org`` and ``ray_dir``): all rays of a block of samples in one
evaluation, which stores only the hit distance. ``bvh`` is the fallback:
``mathutils.bvhtree.BVHTree.ray_cast`` in a Python loop. Everything lives in a private scene, so
a user's open scene is never touched. Both answer in the embree backend's terms
(``distances32`` / ``cast_hits``), so the build's hot loop is the same for every caster.

Where the time goes (bench/blender_path.py): Blender's own Raycast evaluation is ~95 % of the
path; it costs about 6-8 times embree's CPU time per ray (its BVH traversal: ~0.3-0.45 us a
miss near the target, 0.8-1.3 us a hit, against embree's ~0.05 / 0.15 us), and it runs on every
core. Even casting only the rays that hit, it costs 2.7x the whole embree path's CPU.
"""

from __future__ import annotations

import numpy as np

from apcg_core.errors import InputError

from .hits import hits_of

_PREFIX = "APCG raycast"


def _import_bpy():
    try:
        import bpy
    except ImportError as exc:
        raise InputError("the blender backend needs Blender's Python module: run inside "
                         "Blender (blender -b -P ...) or pip install 'apcg[blender]'") from exc
    return bpy


def _socket(sockets, name: str, type_: str | None = None):
    """The socket called ``name`` (and of ``type_``, when several share the name, as typed
    variants do in Blender 3.x-4.0); the enabled one first."""
    found = [s for s in sockets if s.name == name and (type_ is None or s.type == type_)]
    found = [s for s in found if getattr(s, "enabled", True)] or found
    if not found:
        raise RuntimeError(f"Blender node has no socket {name!r} ({type_}); "
                           f"has {[s.name for s in sockets]}")
    return found[0]


def _new_group_socket(tree, name: str, in_out: str, socket_type: str) -> None:
    if hasattr(tree, "interface"):  # Blender 4.0+
        tree.interface.new_socket(name=name, in_out=in_out, socket_type=socket_type)
    elif in_out == "INPUT":  # Blender 3.x
        tree.inputs.new(socket_type, name)
    else:
        tree.outputs.new(socket_type, name)


def _build_node_group(bpy, target_obj):
    """Store Named Attribute (``apcg_dist``, float, points) <- Raycast(target, source position =
    attribute ``ray_org``, direction = attribute ``ray_dir``): one field evaluation per call.

    Only the hit distance is stored: a second Store node (e.g. for "Is Hit") would evaluate the
    Raycast field a second time (measured: 2-4 times slower). A miss reports the ray length, a
    hit less (see :meth:`BlenderCaster.distances32`)."""
    tree = bpy.data.node_groups.new(f"{_PREFIX} nodes", "GeometryNodeTree")
    _new_group_socket(tree, "Geometry", "INPUT", "NodeSocketGeometry")
    _new_group_socket(tree, "Geometry", "OUTPUT", "NodeSocketGeometry")
    nodes, links = tree.nodes, tree.links
    group_in = nodes.new("NodeGroupInput")
    group_out = nodes.new("NodeGroupOutput")

    info = nodes.new("GeometryNodeObjectInfo")
    info.transform_space = "ORIGINAL"  # the mesh in its own (body) frame
    _socket(info.inputs, "Object").default_value = target_obj

    cast = nodes.new("GeometryNodeRaycast")
    cast.data_type = "FLOAT"
    links.new(_socket(info.outputs, "Geometry"), _socket(cast.inputs, "Target Geometry"))
    for attr, socket in (("ray_org", "Source Position"), ("ray_dir", "Ray Direction")):
        named = nodes.new("GeometryNodeInputNamedAttribute")
        named.data_type = "FLOAT_VECTOR"
        _socket(named.inputs, "Name").default_value = attr
        links.new(_socket(named.outputs, "Attribute", "VECTOR"), _socket(cast.inputs, socket))
    ray_length = _socket(cast.inputs, "Ray Length")

    store = nodes.new("GeometryNodeStoreNamedAttribute")
    store.data_type = "FLOAT"
    store.domain = "POINT"
    _socket(store.inputs, "Name").default_value = "apcg_dist"
    links.new(_socket(group_in.outputs, "Geometry"), _socket(store.inputs, "Geometry"))
    links.new(_socket(cast.outputs, "Hit Distance"), _socket(store.inputs, "Value", "VALUE"))
    links.new(_socket(store.outputs, "Geometry"), _socket(group_out.inputs, "Geometry"))
    return tree, ray_length


# The ray mesh's size, in steps of this many points: made again only when a call has more rays
# than it holds (one point is always left over), or fewer than a quarter. The points past a
# call's rays hold rays that miss at once.
_CAPACITY_STEP = 8192
# Unused points: far outside any catalog mesh (tens of metres), pointing away from it, so that
# Blender's BVH rejects them at its root box (~40 ns each).
_DEAD_ORIGIN = np.float32(1.0e6)


class BlenderCaster:
    """First-hit distances along rays in the mesh's frame, by Blender's ray casting.

    The Geometry Nodes method keeps one private scene, target object and ray object per caster
    (one per type): a call writes the rays into the ray mesh's ``ray_org`` / ``ray_dir``
    attributes (the mesh is resized only when a call needs more points, or far fewer),
    evaluates the depsgraph once and reads the distances back into a preallocated array."""

    def __init__(self, mesh, method: str = "geometry-nodes") -> None:
        if method not in ("geometry-nodes", "bvh"):
            raise InputError(f"blender ray-casting method must be 'geometry-nodes' or 'bvh', "
                             f"got {method!r}")
        if len(mesh.faces) == 0:
            raise InputError("cannot ray-cast a mesh with no faces")
        self.method = method
        self.name = "blender" if method == "geometry-nodes" else "blender-bvh"
        self._bpy = bpy = _import_bpy()
        verts = mesh.vertices.astype(np.float32)
        faces = mesh.faces.astype(np.int32)
        self._verts, self._faces = verts, faces
        self._bvh = None  # mathutils' BVH: the bvh method's caster, else made when first needed
        if method == "bvh":
            from mathutils.bvhtree import BVHTree
            self._bvh = BVHTree.FromPolygons(verts.tolist(), faces.tolist(), all_triangles=True)
            return
        self._scene = bpy.data.scenes.new(_PREFIX)
        target_mesh = bpy.data.meshes.new(f"{_PREFIX} target")
        target_mesh.from_pydata(verts.tolist(), [], faces.tolist())
        target_mesh.update()
        target_mesh.validate()
        self._target = bpy.data.objects.new(f"{_PREFIX} target", target_mesh)
        self._rays_mesh = bpy.data.meshes.new(f"{_PREFIX} rays")
        self._rays = bpy.data.objects.new(f"{_PREFIX} rays", self._rays_mesh)
        self._scene.collection.objects.link(self._target)
        self._scene.collection.objects.link(self._rays)
        self._tree, self._ray_length = _build_node_group(bpy, self._target)
        mod = self._rays.modifiers.new("APCG raycast", "NODES")
        mod.node_group = self._tree
        self._view_layer = self._scene.view_layers[0]
        self._length = None  # the Raycast node's current ray length
        self._capacity = 0
        self._used = 0  # rays written by the last call (the points after them are dead)
        self._org = self._dir = self._dist = None

    # --- Geometry Nodes ----------------------------------------------------------------------
    def _grow(self, n: int) -> None:
        cap = -(-(n + 1) // _CAPACITY_STEP) * _CAPACITY_STEP
        me = self._rays_mesh
        me.clear_geometry()
        me.vertices.add(cap)
        for name in ("ray_org", "ray_dir"):
            if me.attributes.get(name) is None:
                me.attributes.new(name, "FLOAT_VECTOR", "POINT")
        self._org = np.full((cap, 3), _DEAD_ORIGIN, np.float32)
        self._dir = np.zeros((cap, 3), np.float32)
        self._dir[:, 0] = 1.0
        self._dist = np.empty(cap, np.float32)
        self._capacity, self._used = cap, 0

    def _distances(self, origin: np.ndarray, direction: np.ndarray, t_max: float) -> np.ndarray:
        """Blender's float32 hit distance of each ray (the ray length where it misses): a view
        of this caster's buffer, valid until the next call."""
        n = len(origin)
        if n >= self._capacity or n < self._capacity // 4:
            self._grow(n)
        org, dir_ = self._org, self._dir
        org[:n] = origin
        dir_[:n] = direction
        if self._used > n:  # points of the last call that this one does not use: dead again
            org[n:self._used] = _DEAD_ORIGIN
            dir_[n:self._used] = (1.0, 0.0, 0.0)
        self._used = n
        me = self._rays_mesh
        attrs = me.attributes
        attrs["ray_org"].data.foreach_set("vector", org.reshape(-1))
        attrs["ray_dir"].data.foreach_set("vector", dir_.reshape(-1))
        me.update()
        length = float(np.float32(t_max))
        if length != self._length:
            self._ray_length.default_value = length
            self._length = length
        self._view_layer.update()  # evaluates the ray object's modifier: the ray casting
        evaluated = self._rays.evaluated_get(self._view_layer.depsgraph).data
        evaluated.attributes["apcg_dist"].data.foreach_get("value", self._dist)
        if self._dist[-1] != np.float32(length):  # the last point is always a miss
            raise RuntimeError(f"Blender {self._bpy.app.version_string}: the Raycast node "
                               f"reported {self._dist[-1]!r} for a ray that misses, not the ray "
                               f"length {length!r}; the blender backend cannot tell hits apart")
        return self._dist[:n]

    def distances32(self, origin: np.ndarray, direction: np.ndarray, limit: np.float32,
                    out: np.ndarray | None = None) -> np.ndarray:
        """Float32 rays (n, 3) -> float32 t in units of each direction's length, exactly
        ``limit`` where nothing is hit before it: the embree backend's ``distances32``, which
        the build's compiled loops read (:func:`dataset_builder.rays.cast_cells`).

        Blender normalises the direction and measures the distance in scene units; a miss
        reports the ray length, ``limit``. Rays start outside the target's bounding sphere and
        end beyond it, so a hit is shorter than the ray by at least the start margin: distances
        below ``limit`` are hits, and only they are divided by the direction's length (float32
        unit directions are within ~1e-7 of length 1). Written to ``out`` (float32, n) when
        given, else a view of this caster's buffer, valid until its next call."""
        if len(origin) == 0:
            return np.zeros(0, np.float32)
        if self.method == "bvh":
            t = self._cast_bvh(origin, direction, float(limit))
            dist = np.where(np.isfinite(t), t, limit).astype(np.float32)
        else:
            dist = self._distances(origin, direction, limit)
        if out is not None:
            out[...] = dist
            dist = out
        hit = np.flatnonzero(dist < limit)
        if len(hit):
            norm = np.sqrt((direction[hit].astype(np.float64) ** 2).sum(axis=1))
            dist[hit] = dist[hit].astype(np.float64) / norm
        return dist

    def cast(self, origin: np.ndarray, direction: np.ndarray, t_max: float) -> np.ndarray:
        """Distance (float64) to the first surface along each unit direction, inf if none."""
        n = len(origin)
        if n == 0:
            return np.zeros(0)
        o = np.ascontiguousarray(origin, dtype=np.float32)
        d = np.ascontiguousarray(direction, dtype=np.float32)
        if self.method == "bvh":
            return self._cast_bvh(o, d, t_max)
        ray, t_hit = self.cast_hits(o, d, t_max)
        t = np.full(n, np.inf)
        t[ray] = t_hit
        return t

    def cast_hits(self, origin: np.ndarray, direction: np.ndarray,
                  t_max: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`cast` for float32 rays, answering only the hits: (ray index, float64
        distance), the embree backend's arithmetic on :meth:`distances32`."""
        return hits_of(self.distances32, origin, direction, t_max)

    def triangles(self, origin: np.ndarray, direction: np.ndarray,
                  limit: np.float32) -> np.ndarray:
        """Index of the triangle each float32 ray hits first before ``limit``, -1 where none,
        by Blender's BVH (``mathutils.bvhtree``) over this caster's triangles: for the few
        rays of :func:`dataset_builder.refine.refine_ranges`, so a Python loop is enough."""
        from mathutils import Vector
        if self._bvh is None:
            from mathutils.bvhtree import BVHTree
            self._bvh = BVHTree.FromPolygons(self._verts.tolist(), self._faces.tolist(),
                                             all_triangles=True)
        out = np.full(len(origin), -1, np.int64)
        ray_cast = self._bvh.ray_cast
        length = float(limit)
        for i, (oi, di) in enumerate(zip(np.asarray(origin, np.float32).tolist(),
                                         np.asarray(direction, np.float32).tolist(),
                                         strict=True)):
            hit = ray_cast(Vector(oi), Vector(di), length)
            if hit[2] is not None:
                out[i] = hit[2]
        return out

    def _cast_bvh(self, o, d, t_max) -> np.ndarray:
        from mathutils import Vector
        t = np.full(len(o), np.inf)
        ray_cast = self._bvh.ray_cast
        for i, (oi, di) in enumerate(zip(o.tolist(), d.tolist(), strict=True)):
            hit = ray_cast(Vector(oi), Vector(di), t_max)
            if hit[0] is not None:
                t[i] = hit[3]
        return t

    def close(self) -> None:
        """Remove this caster's objects from Blender's data (the meshes and the node group)."""
        if self.method == "bvh":
            return
        bpy = self._bpy
        for obj in (self._rays, self._target):
            data = obj.data
            bpy.data.objects.remove(obj)
            bpy.data.meshes.remove(data)
        bpy.data.node_groups.remove(self._tree)
        bpy.data.scenes.remove(self._scene)
