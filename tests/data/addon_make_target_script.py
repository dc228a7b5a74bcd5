"""Run inside a real Blender window (tests/test_addon_targets.py): the box aircraft of
box_aircraft.py (Mirror modifier, rotated, scaled) made a target with the Make Target operator,
scanned, the APCG sidebar tab opened on the target, and a screenshot taken. Writes a JSON
report to the first path after `--` and the screenshot to the second."""

import sys
import traceback
from pathlib import Path

import addon_utils
import bpy

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import box_aircraft as box  # noqa: E402
from window_script import finish as _finish  # noqa: E402
from window_script import frame, override, view3d  # noqa: E402

ARGS = sys.argv[sys.argv.index("--") + 1:]
OUT, PNG = ARGS[0], ARGS[1]
report = {}
state = {}


def finish(error=None):
    _finish(report, OUT, error)


def setup():
    for obj in list(bpy.data.objects):  # the startup cube, camera and light
        bpy.data.objects.remove(obj)
    assert addon_utils.enable("apcg_blender", default_set=True) is not None
    models = bpy.data.collections.new("Models")
    bpy.context.scene.collection.children.link(models)
    src = box.add_box_aircraft(collection=models)
    state["src"], state["before"] = src, [list(r) for r in src.matrix_world]
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    src.select_set(True)
    bpy.context.view_layer.objects.active = src
    win, area, region = view3d()
    area.spaces.active.show_region_ui = True


def click_make_target():
    """Click the panel's "Make Target of Box jet" button (the third row of the APCG tab), as
    a user does: the operator runs from the UI, so its redo panel shows the guessed axes."""
    win, area, _ = view3d()
    ui = next(r for r in area.regions if r.type == "UI")
    x, y = ui.x + (ui.width - 26) // 2, ui.y + ui.height - 87
    win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
    win.event_simulate(type="LEFTMOUSE", value="PRESS", x=x, y=y)
    win.event_simulate(type="LEFTMOUSE", value="RELEASE", x=x, y=y)
    win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=area.x + 600, y=area.y + 500)


def after_make_target():
    from apcg_blender.objects import AXES_KEY, axes_label, is_target
    src = state["src"]
    target = bpy.context.active_object
    report["clicked"] = is_target(target)
    if not report["clicked"]:  # the button was not where expected: run it from Python
        with override():
            report["make_target"] = sorted(bpy.ops.apcg.make_target())
        target = bpy.context.active_object
    else:
        report["make_target"] = ["FINISHED"]
    ops = bpy.context.window_manager.operators
    if len(ops) and ops[-1].bl_idname == "APCG_OT_make_target":  # its redo panel's values
        p = ops[-1].properties
        report["redo_axes"] = [p.forward, p.up, p.guess_axes, p.axes_note]
    report["axes"] = axes_label(target)
    report["extents"] = list(target[AXES_KEY]["extents_m"])
    report["source_untouched"] = ([list(r) for r in src.matrix_world] == state["before"]
                                  and src.get("apcg_pose") is None
                                  and len(src.modifiers) == 1)
    # the pose, as a user sets it in the panel
    target.apcg_target.range_m = 1500.0
    target.apcg_target.yaw_deg = 35.0
    target.apcg_target.roll_deg = 3.0
    with override():
        report["scan"] = sorted(bpy.ops.apcg.scan())
    cloud = next(o for o in bpy.data.objects if o.get("apcg_cloud") is not None)
    report["cloud_points"] = len(cloud.data.vertices)
    from apcg_blender import api
    api.set_point_radius(cloud, 0.12)
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    bpy.context.view_layer.objects.active = target  # active, not selected: no outline
    bpy.context.view_layer.update()
    frame(target, cloud, distance=58.0, pitch_deg=64, yaw_deg=-30)


def open_tab():
    """Click the sidebar's APCG tab (Blender 3.4 has no Python API for the active tab): the
    tab strip runs down the region's right edge, APCG is the 4th tab (Item, Tool, View)."""
    win, area, _ = view3d()
    ui = next(r for r in area.regions if r.type == "UI")
    x, y = ui.x + ui.width - 13, ui.y + ui.height - 161
    win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
    win.event_simulate(type="LEFTMOUSE", value="PRESS", x=x, y=y)
    win.event_simulate(type="LEFTMOUSE", value="RELEASE", x=x, y=y)
    # then park the pointer over the viewport, away from the panel
    win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=area.x + 40, y=area.y + 40)
    for a in win.screen.areas:
        a.tag_redraw()


def shoot():
    win, area, region = view3d()
    with bpy.context.temp_override(window=win, area=area, region=region):
        bpy.ops.screen.screenshot(filepath=PNG)
    report["screenshot"] = PNG


PLAN = [(1.0, setup), (0.5, open_tab), (1.0, click_make_target), (1.5, after_make_target),
        (2.0, shoot), (0.5, finish)]


def driver():
    try:
        _, fn = PLAN.pop(0)
        fn()
    except Exception:  # noqa: BLE001 - handed to the test
        finish(traceback.format_exc())
        return None
    return PLAN[0][0] if PLAN else None


bpy.app.timers.register(driver, first_interval=PLAN[0][0])
