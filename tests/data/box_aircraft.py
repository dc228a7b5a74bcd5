"""An aircraft made of boxes, as an artist might place it in Blender: nose along world -Y, up
+Z, wings along X, the fin at the tail (+Y) on top. Used by tests/test_addon_targets.py and,
inside a real Blender window, by tests/data/addon_make_target_script.py (numpy and bpy only).

In the scene it is half an aircraft (x >= 0) with a Mirror modifier, a non-uniform scale and
a rotation: only the evaluated, transformed mesh is the whole aircraft at its real size."""

import math

import numpy as np

# (lo, hi) corners in world-oriented axes (m): nose at y = -15, tail at y = +15
BOXES = (
    ((-1.5, -15.0, -1.5), (1.5, 15.0, 1.5)),  # fuselage: 30 m long
    ((-14.0, -3.0, -0.25), (14.0, 1.0, 0.25)),  # wing: 28 m span
    ((-5.0, 11.0, 0.8), (5.0, 14.5, 1.2)),  # tailplane
    ((-0.2, 10.0, 1.5), (0.2, 15.0, 6.0)),  # fin on top of the tail: 7.5 m high in all
)
LENGTH_M, SPAN_M, HEIGHT_M = 30.0, 28.0, 7.5
ROTATION_Z_DEG = 90.0
SCALE = (2.0, 0.5, 1.5)
MIRROR_LOCAL_AXIS = 1  # world x -> local y under the rotation above

_CUBE_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                        [2, 3, 7], [2, 7, 6], [1, 2, 6], [1, 6, 5], [0, 4, 7], [0, 7, 3]])


def box_mesh(boxes=BOXES):
    """(vertices (8n, 3), faces (12n, 3)) of closed boxes, wound outward."""
    verts, faces = [], []
    for i, (lo, hi) in enumerate(boxes):
        (x0, y0, z0), (x1, y1, z1) = lo, hi
        verts.append([(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0),
                      (x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)])
        faces.append(_CUBE_FACES + 8 * i)
    return np.array(verts, float).reshape(-1, 3), np.concatenate(faces)


def half_boxes(boxes=BOXES):
    """The x >= 0 half of each box (the Mirror modifier makes the other)."""
    return tuple(((0.0, lo[1], lo[2]), hi) for lo, hi in boxes)


def world_to_local(v: np.ndarray) -> np.ndarray:
    """Undo the object's rotation (about z) and scale: local coordinates of world-oriented
    points."""
    a = math.radians(ROTATION_Z_DEG)
    rot = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    return (v @ rot) / np.array(SCALE)  # rot.T @ v, then / scale


def add_box_aircraft(name="Box jet", location=(0.0, 20.0, 1.0), collection=None):
    """The half aircraft with a Mirror modifier, rotated and scaled, in ``collection``."""
    import bpy
    v, f = box_mesh(half_boxes())
    me = bpy.data.meshes.new(name)
    me.from_pydata(world_to_local(v).tolist(), [], f.tolist())
    me.update()
    obj = bpy.data.objects.new(name, me)
    (collection or bpy.context.scene.collection).objects.link(obj)
    mod = obj.modifiers.new("Mirror", "MIRROR")
    mod.use_axis = [i == MIRROR_LOCAL_AXIS for i in range(3)]
    mod.use_mirror_merge = False
    obj.rotation_euler = (0.0, 0.0, math.radians(ROTATION_Z_DEG))
    obj.scale = SCALE
    obj.location = location
    bpy.context.view_layer.update()
    return obj
