"""For scripts that drive a real Blender window (the docs' screenshots, the add-on's window
tests): find the 3D view, frame a target with its cloud, write a JSON report and quit. Plain
bpy, no apcg import: it runs in Debian's Blender with its own Python."""

import json
import math

import bpy


def view3d():
    """(window, area, region) of the first 3D viewport."""
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                region = next(r for r in area.regions if r.type == "WINDOW")
                return window, area, region
    raise RuntimeError("no 3D viewport")


def override():
    """A context override on the 3D viewport, for operators run from a script."""
    window, area, region = view3d()
    return bpy.context.temp_override(window=window, area=area, region=region)


def frame(target, cloud, distance: float, pitch_deg: float, yaw_deg: float):
    """Solid grey target, orange cloud, seen from ``distance`` at the given view angles;
    returns the viewport's area."""
    from mathutils import Euler

    _, area, _ = view3d()
    space = area.spaces.active
    space.clip_start, space.clip_end = 0.5, 1e5
    space.shading.type = "SOLID"
    space.shading.color_type = "OBJECT"
    target.color = (0.6, 0.62, 0.66, 1.0)
    cloud.color = (1.0, 0.55, 0.1, 1.0)
    r3d = space.region_3d
    r3d.view_perspective = "PERSP"
    r3d.view_location = target.matrix_world.translation
    r3d.view_distance = distance
    r3d.view_rotation = Euler((math.radians(pitch_deg), 0.0, math.radians(yaw_deg)),
                              "XYZ").to_quaternion()
    return area


def finish(report: dict, out: str, error=None) -> None:
    """Write ``report`` (with ``error``: None or a traceback) to ``out`` and quit Blender."""
    report["error"] = error
    with open(out, "w") as f:
        json.dump(report, f)
    bpy.ops.wm.quit_blender()
