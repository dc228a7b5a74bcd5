"""Render an aircraft with its scanned lidar cloud in Cycles (the README's picture).

    python tools/render_example.py -o docs/addon_render.png [--size 960 540] [--samples 32]

Runs in the bpy module (pip install 'apcg[blender]'). The add-on is registered from this
checkout; the scene is built through its script API.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def build_scene(type_name: str = "A320neo", range_m: float = 3000.0):
    import bpy
    from mathutils import Vector

    from blender_addon import api
    lidar = api.add_lidar()
    jet = api.add_aircraft(lidar, type_name, range_m=range_m, elevation_deg=3.5,
                           pitch_deg=2.0, yaw_deg=35.0, roll_deg=3.0)
    (cloud,) = api.scan(lidar)
    api.set_point_radius(cloud, 0.12)
    grey = bpy.data.materials.new("Airframe")
    grey.diffuse_color = (0.55, 0.57, 0.6, 1.0)
    if grey.node_tree is None or bpy.app.version < (5, 0, 0):
        grey.use_nodes = True
    bsdf = next(n for n in grey.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    bsdf.inputs["Base Color"].default_value = (0.55, 0.57, 0.6, 1.0)
    jet.data.materials.append(grey)
    bpy.context.view_layer.update()
    centre = jet.matrix_world.translation.copy()
    # look from beside the lidar's line of sight, a little above: the cloud covers the side
    # of the aircraft that faces the lidar
    cam_data = bpy.data.cameras.new("Camera")
    cam_data.lens = 50
    cam_data.clip_end = 1e5
    cam = bpy.data.objects.new("Camera", cam_data)
    bpy.context.scene.collection.objects.link(cam)
    cam.location = centre + Vector((-38.0, -62.0, 22.0))
    direction = centre - cam.location
    cam.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()
    bpy.context.scene.camera = cam
    sun_data = bpy.data.lights.new("Sun", "SUN")
    sun_data.energy = 3.0
    sun = bpy.data.objects.new("Sun", sun_data)
    sun.rotation_euler = (math.radians(40), math.radians(10), math.radians(30))
    bpy.context.scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("Sky")
    world.color = (0.02, 0.03, 0.05)
    bpy.context.scene.world = world
    return jet, cloud


def render(path, size=(960, 540), samples: int = 32) -> Path:
    import bpy

    import blender_addon
    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender_addon.register()
    try:
        build_scene()
        scene = bpy.context.scene
        scene.render.engine = "CYCLES"
        scene.cycles.device = "CPU"
        scene.cycles.samples = samples
        scene.render.resolution_x, scene.render.resolution_y = size
        scene.render.resolution_percentage = 100
        scene.render.image_settings.file_format = "PNG"
        path = Path(path).resolve()
        scene.render.filepath = str(path)
        bpy.ops.render.render(write_still=True)
    finally:
        blender_addon.unregister()
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--size", type=int, nargs=2, default=(960, 540))
    ap.add_argument("--samples", type=int, default=32)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))  # a tool of this checkout, run from anywhere
    print(render(args.output, tuple(args.size), args.samples))
    return 0


if __name__ == "__main__":
    sys.exit(main())
