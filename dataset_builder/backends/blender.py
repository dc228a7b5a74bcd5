"""The ``blender`` backend: Blender's own ray casting, inside bpy (the PyPI module or a running
Blender, e.g. ``blender -b -P``).

``geometry-nodes`` (default) evaluates one Geometry Nodes Raycast over a vertex-only mesh whose
vertices are the ray origins (a ``ray_dir`` attribute holds the directions): all rays of many
samples in one evaluation. ``bvh`` is the fallback: ``mathutils.bvhtree.BVHTree.ray_cast`` in a
Python loop. Everything lives in a private scene, so a user's open scene is never touched.
"""

from __future__ import annotations

import numpy as np

from apcg_core.errors import InputError

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
    tree = bpy.data.node_groups.new(f"{_PREFIX} nodes", "GeometryNodeTree")
    _new_group_socket(tree, "Geometry", "INPUT", "NodeSocketGeometry")
    _new_group_socket(tree, "Geometry", "OUTPUT", "NodeSocketGeometry")
    nodes, links = tree.nodes, tree.links
    group_in = nodes.new("NodeGroupInput")
    group_out = nodes.new("NodeGroupOutput")

    info = nodes.new("GeometryNodeObjectInfo")
    info.transform_space = "ORIGINAL"  # the mesh in its own (body) frame
    _socket(info.inputs, "Object").default_value = target_obj

    direction = nodes.new("GeometryNodeInputNamedAttribute")
    direction.data_type = "FLOAT_VECTOR"
    _socket(direction.inputs, "Name").default_value = "ray_dir"

    cast = nodes.new("GeometryNodeRaycast")
    cast.data_type = "FLOAT"
    links.new(_socket(info.outputs, "Geometry"), _socket(cast.inputs, "Target Geometry"))
    links.new(_socket(direction.outputs, "Attribute", "VECTOR"),
              _socket(cast.inputs, "Ray Direction"))
    ray_length = _socket(cast.inputs, "Ray Length")

    geometry = _socket(group_in.outputs, "Geometry")
    for attr, data_type, out_name in (("apcg_hit", "BOOLEAN", "Is Hit"),
                                      ("apcg_dist", "FLOAT", "Hit Distance")):
        store = nodes.new("GeometryNodeStoreNamedAttribute")
        store.data_type = data_type
        store.domain = "POINT"
        _socket(store.inputs, "Name").default_value = attr
        links.new(geometry, _socket(store.inputs, "Geometry"))
        value_type = "BOOLEAN" if data_type == "BOOLEAN" else "VALUE"
        links.new(_socket(cast.outputs, out_name), _socket(store.inputs, "Value", value_type))
        geometry = _socket(store.outputs, "Geometry")
    links.new(geometry, _socket(group_out.inputs, "Geometry"))
    return tree, ray_length


class BlenderCaster:
    """First-hit distances along rays in the mesh's frame, by Blender's ray casting."""

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

    def cast(self, origin: np.ndarray, direction: np.ndarray, t_max: float) -> np.ndarray:
        """Distance (float64) to the first surface along each unit direction, inf if none."""
        n = len(origin)
        if n == 0:
            return np.zeros(0)
        o = np.ascontiguousarray(origin, dtype=np.float32)
        d = np.ascontiguousarray(direction, dtype=np.float32)
        if self.method == "bvh":
            return self._cast_bvh(o, d, t_max)
        me = self._rays_mesh
        me.clear_geometry()
        me.vertices.add(n)
        me.vertices.foreach_set("co", o.ravel())
        attr = me.attributes.get("ray_dir") or me.attributes.new("ray_dir", "FLOAT_VECTOR",
                                                                 "POINT")
        attr.data.foreach_set("vector", d.ravel())
        me.update()
        self._ray_length.default_value = float(t_max)
        view_layer = self._scene.view_layers[0]
        view_layer.update()  # creates the private scene's depsgraph on first use, then updates
        depsgraph = view_layer.depsgraph
        evaluated = self._rays.evaluated_get(depsgraph)
        emesh = evaluated.data
        hit = np.zeros(n, dtype=bool)
        dist = np.zeros(n, dtype=np.float32)
        emesh.attributes["apcg_hit"].data.foreach_get("value", hit)
        emesh.attributes["apcg_dist"].data.foreach_get("value", dist)
        # Blender normalises the direction and measures the distance in scene units.
        t = np.where(hit, dist.astype(np.float64), np.inf)
        return t

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
