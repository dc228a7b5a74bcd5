"""Run inside a real Blender window (tests/test_addon_gui.py): the modal scan with its progress,
undo and redo, and Esc to cancel. Writes a JSON report to the path after `--`."""

import sys
import traceback
from pathlib import Path

import addon_utils
import bpy

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
from window_script import finish as _finish  # noqa: E402
from window_script import override  # noqa: E402

OUT = sys.argv[sys.argv.index("--") + 1]
N_TARGETS = 12
report = {}


def clouds() -> int:
    return sum(o.get("apcg_cloud") is not None for o in bpy.data.objects)


def finish(error=None):
    _finish(report, OUT, error)

def setup():
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    assert addon_utils.enable("apcg_blender", default_set=True) is not None
    from apcg_blender import api
    lidar = api.add_lidar()
    for i in range(N_TARGETS):
        api.add_aircraft(lidar, "A320neo", range_m=3000.0 + 500 * i, elevation_deg=3.5,
                         yaw_deg=-40 + 7 * i, azimuth_deg=0.5 * i)
    bpy.context.view_layer.objects.active = lidar
    with override():
        bpy.ops.ed.undo_push(message="targets")
        report["invoke"] = sorted(bpy.ops.apcg.scan("INVOKE_DEFAULT"))
    report["right_after_invoke"] = clouds()  # modal: nothing made yet


def after_scan():
    report["after_modal_scan"] = clouds()
    report["scenes_after_scan"] = len(bpy.data.scenes)  # the simulator's private scene is gone
    with override():
        bpy.ops.ed.undo()
    report["after_undo"] = clouds()
    with override():
        bpy.ops.ed.redo()
    report["after_redo"] = clouds()
    for o in [o for o in bpy.data.objects if o.get("apcg_cloud") is not None]:
        bpy.data.objects.remove(o)
    bpy.context.view_layer.objects.active = next(o for o in bpy.data.objects
                                                 if o.get("apcg_lidar_params") is not None)
    with override():
        report["invoke_again"] = sorted(bpy.ops.apcg.scan("INVOKE_DEFAULT"))


def press_esc():
    report["before_esc"] = clouds()  # some targets done, not all
    win = bpy.context.window_manager.windows[0]
    win.event_simulate(type="ESC", value="PRESS")
    win.event_simulate(type="ESC", value="RELEASE")


def after_esc():
    report["after_esc"] = clouds()
    report["scenes_after_esc"] = len(bpy.data.scenes)


# (seconds before the step, or a condition to wait for; the step)
PLAN = [(1.0, setup), (lambda: clouds() >= N_TARGETS, after_scan),
        (lambda: clouds() >= 2, press_esc), (2.0, after_esc)]


def driver():
    """Runs the plan's steps from timers, waiting (30 s at most) on a step's condition."""
    try:
        wait, fn = PLAN[0]
        if callable(wait) and not wait() and driver.waited < 30.0:
            driver.waited += 0.02
            return 0.02
        driver.waited = 0.0
        PLAN.pop(0)
        fn()
    except Exception:  # noqa: BLE001 - handed to the test
        finish(traceback.format_exc())
        return None
    if not PLAN:
        finish()
        return None
    return PLAN[0][0] if not callable(PLAN[0][0]) else 0.02


driver.waited = 0.0
bpy.app.timers.register(driver, first_interval=PLAN[0][0])
