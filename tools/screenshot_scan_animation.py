"""Inside a real Blender window: enable the add-on, animate a fighter passing in front of an
airliner, run Scan Animation (the panel's operator: rows fired 1 ms apart), let the imported
sequence play on the timeline and save a screenshot of the window at three of its frames.

    bash tools/screenshot_scan_animation.sh docs/scan_animation.png

(the wrapper starts Xvfb, installs the legacy zip, clicks the APCG sidebar tab with xdotool and
puts the three screenshots side by side). Prints what worked.
"""

import sys
import tempfile
from pathlib import Path

import addon_utils
import bpy

sys.path.insert(0, str(Path(__file__).resolve().parent))
from window_script import frame, override, view3d  # noqa: E402

OUT = sys.argv[sys.argv.index("--") + 1] if "--" in sys.argv else "/tmp/apcg_anim"
MODULE = "apcg_blender"
FRAMES = (1, 3, 5)


def setup():
    for obj in list(bpy.data.objects):  # the startup cube, camera and light
        bpy.data.objects.remove(obj)
    if addon_utils.enable(MODULE, default_set=True) is None:
        raise RuntimeError(f"could not enable {MODULE}")
    from apcg_blender import api
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end, scene.render.fps = 1, 5, 10
    lidar = api.add_lidar()
    jet = api.add_aircraft(lidar, "A320neo", range_m=3150.0, elevation_deg=3.5, yaw_deg=60.0)
    fighter = api.add_aircraft(lidar, "F-16C Fighting Falcon", range_m=3000.0,
                               elevation_deg=3.49, yaw_deg=-90.0)
    x, y, z = fighter.location
    for f, dx in ((1, -16.0), (5, 16.0)):  # across the line of sight, in front of the jet
        fighter.location = (x + dx, y, z)
        fighter.keyframe_insert("location", frame=f)
    for o in bpy.data.objects:
        if o is not None and o.name in bpy.context.view_layer.objects:
            o.select_set(False)
    lidar.select_set(True)
    bpy.context.view_layer.objects.active = lidar
    out = Path(tempfile.mkdtemp()) / "sequence"
    with override():
        r = bpy.ops.apcg.scan_animation(directory=str(out), pattern="rows", line_time_s=1e-3)
    print(f"APCG: scan_animation {r}")
    clouds = sorted((o for o in bpy.data.objects if api.is_cloud(o)), key=lambda o: o.name)
    print(f"APCG: {len(clouds)} cloud objects")
    for c in clouds:
        api.set_point_radius(c, 0.3)
    area = frame(jet, clouds[0], distance=150.0, pitch_deg=84, yaw_deg=-12)
    for c in clouds:
        c.color = (1.0, 0.55, 0.1, 1.0)
    fighter.color = (0.35, 0.37, 0.42, 1.0)
    # between the two aircraft, looking from near the lidar along its line of sight
    mid = (jet.matrix_world.translation + fighter.matrix_world.translation) / 2
    area.spaces.active.region_3d.view_location = mid
    area.spaces.active.show_region_ui = True
    ui = next(r for r in area.regions if r.type == "UI")
    print(f"APCG: sidebar region x={ui.x} y={ui.y} w={ui.width} h={ui.height} "
          f"window h={view3d()[0].height}")
    try:
        ui.active_panel_category = "APCG"
        print("APCG: sidebar tab set through Region.active_panel_category")
    except (AttributeError, TypeError) as exc:
        print(f"APCG: cannot select the sidebar tab from Python here ({exc})")
    scene.frame_set(FRAMES[0])
    return None


def shot(k):
    def run():
        scene = bpy.context.scene
        scene.frame_set(FRAMES[k])
        shown = [o.name for o in bpy.data.objects if o.name.startswith("APCG sequence")
                 and not o.hide_viewport]
        print(f"APCG: frame {FRAMES[k]} shows {shown}")
        window, area, region = view3d()
        with bpy.context.temp_override(window=window, area=area, region=region):
            bpy.ops.screen.screenshot(filepath=f"{OUT}_{k}.png")
        print(f"APCG: screenshot {OUT}_{k}.png")
        return None
    return run


def quit_():
    bpy.ops.wm.quit_blender()


def main():
    bpy.app.timers.register(setup, first_interval=1.0)
    for k in range(len(FRAMES)):
        bpy.app.timers.register(shot(k), first_interval=8.0 + 2.0 * k)
    bpy.app.timers.register(quit_, first_interval=8.0 + 2.0 * len(FRAMES) + 1.0)


main()
