"""Properties: the lidar's parameters (stored), and a target's pose in display units (computed:
read from and written to the target's double-precision pose, so the panel and the viewport
always show the same condition).

No `from __future__ import annotations` here: Blender reads the annotations as objects."""

import math

import bpy
from bpy.props import FloatProperty, IntProperty, PointerProperty, StringProperty

from apcg_core.errors import InputError

from .objects import POSE_KEY, is_target, panel_pose, set_pose


class APCG_PG_lidar(bpy.types.PropertyGroup):
    r_alpha_deg: FloatProperty(name="R alpha (deg)", description="Azimuth resolution",
                               default=0.004, min=1e-6, max=1.0, precision=5)
    r_beta_deg: FloatProperty(name="R beta (deg)", description="Elevation resolution",
                              default=0.0076, min=1e-6, max=1.0, precision=5)
    range_resolution_m: FloatProperty(name="R r (m)", description="Range resolution "
                                      "(time-bin width)", default=0.15, min=1e-4, max=100.0,
                                      precision=3)
    width: IntProperty(name="W", description="Azimuth cells of the window", default=256,
                       min=2, max=16384)
    height: IntProperty(name="H", description="Elevation cells of the window", default=64,
                        min=2, max=16384)
    sensor: StringProperty(name="Sensor", default="ideal",
                           description="What the lidar records (SPEC section 8): ideal (one "
                           "point per cell, no photon statistics), a preset (1064nm-day, "
                           "1064nm-night, 1550nm-day, 1550nm-night) or a TOML file with a "
                           "[sensor] table")
    seed: IntProperty(name="Photon seed", default=0, min=0,
                      description="Seed of the photon draws: the same seed, the same cloud")


def _pose_prop(key: str, label: str, degrees: bool, lo: float, hi: float, descr: str):
    def get(self):
        obj = self.id_data
        pose = panel_pose(obj) if is_target(obj) else None
        if pose is None:  # nothing readable: Scan names why
            return 0.0
        v = pose[key]
        return math.degrees(v) if degrees else v

    def set_(self, value):
        obj = self.id_data
        p = panel_pose(obj) if is_target(obj) else None
        if p is None:
            return
        p[key] = math.radians(value) if degrees else float(value)
        try:
            set_pose(obj, **p)
        except InputError:  # a value no pose takes (range 0...): the target stays as it was
            return

    return FloatProperty(name=label, description=descr, get=get, set=set_, soft_min=lo,
                         soft_max=hi, precision=3 if degrees else 2,
                         unit="NONE")


class APCG_PG_target(bpy.types.PropertyGroup):
    range_m: _pose_prop("range_m", "Range (m)", False, 50.0, 20000.0, "Slant range r0")
    elevation_deg: _pose_prop("elevation", "Elevation (deg)", True, -89.0, 89.0,
                              "Elevation beta0 of the centre of mass")
    azimuth_deg: _pose_prop("azimuth", "Azimuth (deg)", True, -180.0, 180.0,
                            "Turn about the lidar's vertical (not part of the condition: the "
                            "lidar tracks its target)")
    pitch_deg: _pose_prop("pitch", "Pitch (deg)", True, -90.0, 90.0, "+ raises the nose")
    yaw_deg: _pose_prop("yaw", "Yaw (deg)", True, -180.0, 180.0, "+ swings the nose to +X")
    roll_deg: _pose_prop("roll", "Roll (deg)", True, -180.0, 180.0,
                         "+ lowers the right wing")


CLASSES = (APCG_PG_lidar, APCG_PG_target)


def register() -> None:
    for c in CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Object.apcg_lidar = PointerProperty(type=APCG_PG_lidar)
    bpy.types.Object.apcg_target = PointerProperty(type=APCG_PG_target)


def unregister() -> None:
    del bpy.types.Object.apcg_target
    del bpy.types.Object.apcg_lidar
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)


__all__ = ["POSE_KEY", "register", "unregister"]
