"""Inside a real Blender window: enable the add-on, scan an aircraft, open the APCG sidebar
tab, frame the aircraft and its cloud, save a screenshot, quit.

    bash tools/screenshot_gui.sh docs/addon_screenshot.png

(the wrapper starts Xvfb, installs the legacy zip from tools/build_addon.py into a scratch
scripts folder, and clicks the APCG sidebar tab with xdotool: Blender 3.4 has no Python API
for the active sidebar tab). Prints what worked.
"""

import sys
from pathlib import Path

import addon_utils
import bpy

sys.path.insert(0, str(Path(__file__).resolve().parent))
from window_script import frame, view3d  # noqa: E402

OUT = sys.argv[sys.argv.index("--") + 1] if "--" in sys.argv else "/tmp/apcg_screenshot.png"
MODULE = "apcg_blender"


def setup():
    for obj in list(bpy.data.objects):  # the startup cube, camera and light
        bpy.data.objects.remove(obj)
    if addon_utils.enable(MODULE, default_set=True) is None:
        raise RuntimeError(f"could not enable {MODULE}")
    from apcg_blender import api
    lidar = api.add_lidar()
    jet = api.add_aircraft(lidar, "A320neo", range_m=3000.0, elevation_deg=3.5, pitch_deg=2.0,
                           yaw_deg=35.0, roll_deg=3.0)
    (cloud,) = api.scan(lidar)
    api.set_point_radius(cloud, 0.12)
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    jet.select_set(True)
    bpy.context.view_layer.objects.active = jet
    bpy.context.view_layer.update()
    area = frame(jet, cloud, distance=62.0, pitch_deg=68, yaw_deg=-28)
    area.spaces.active.show_region_ui = True
    ui = next(r for r in area.regions if r.type == "UI")
    # where the sidebar's tab strip is, for a click from outside (xdotool) where Python can't
    print(f"APCG: sidebar region x={ui.x} y={ui.y} w={ui.width} h={ui.height} "
          f"window h={view3d()[0].height}")
    try:
        ui.active_panel_category = "APCG"
        print("APCG: sidebar tab set through Region.active_panel_category")
    except (AttributeError, TypeError) as exc:
        print(f"APCG: cannot select the sidebar tab from Python here ({exc})")
    return None  # run once


def shoot():
    window, area, region = view3d()
    with bpy.context.temp_override(window=window, area=area, region=region):
        bpy.ops.screen.screenshot(filepath=OUT)
    print(f"APCG: screenshot {OUT}")
    return None


def quit_():
    bpy.ops.wm.quit_blender()


def main():
    bpy.app.timers.register(setup, first_interval=1.0)
    bpy.app.timers.register(shoot, first_interval=5.0)
    bpy.app.timers.register(quit_, first_interval=7.0)


main()
