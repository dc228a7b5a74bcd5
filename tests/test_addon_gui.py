"""The add-on in a real Blender window (Debian's blender 3.4.1 under Xvfb): the modal scan runs
in chunks to the end, undo and redo take its clouds away and back, Esc cancels a running scan
and removes what it had made."""

import json
import os
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def display():
    xvfb = shutil.which("Xvfb")
    if xvfb is None or shutil.which("blender") is None:
        pytest.skip("needs Xvfb and blender (apt-get install xvfb blender python3-numpy)")
    num = f":{90 + os.getpid() % 9}"
    proc = subprocess.Popen([xvfb, num, "-screen", "0", "1280x800x24", "+extension", "GLX"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(1.0)
    yield num
    proc.terminate()
    proc.wait(timeout=10)


def test_modal_scan_undo_and_escape_in_a_window(tmp_path, display):
    dist = tmp_path / "dist"
    subprocess.run([sys.executable, str(ROOT / "tools" / "build_addon.py"), "--out", str(dist),
                    "--legacy-only"], check=True, capture_output=True)
    with zipfile.ZipFile(next(dist.glob("apcg-legacy-*.zip"))) as z:
        z.extractall(tmp_path / "scripts" / "addons")
    start = tmp_path / "start.blend"  # opening a file skips the splash screen
    subprocess.run(["blender", "-b", "--factory-startup", "--python-expr",
                    f"import bpy; bpy.ops.wm.save_as_mainfile(filepath={str(start)!r})"],
                   check=True, capture_output=True)
    report = tmp_path / "report.json"
    env = dict(os.environ, DISPLAY=display, BLENDER_USER_SCRIPTS=str(tmp_path / "scripts"))
    env.pop("PYTHONPATH", None)
    r = subprocess.run(["blender", "--factory-startup", "--enable-event-simulate", str(start),
                        "-P", str(ROOT / "tests" / "data" / "addon_gui_script.py"), "--",
                        str(report)], env=env, capture_output=True, text=True, timeout=300)
    assert report.exists(), (r.stdout[-2000:], r.stderr[-2000:])
    rep = json.loads(report.read_text())
    assert rep["error"] is None, rep["error"]
    assert rep["invoke"] == ["RUNNING_MODAL"] and rep["right_after_invoke"] == 0
    assert rep["after_modal_scan"] == 12
    assert rep["after_undo"] == 0 and rep["after_redo"] == 12
    assert rep["invoke_again"] == ["RUNNING_MODAL"]
    assert 2 <= rep["before_esc"] < 12 and rep["after_esc"] == 0
    assert rep["scenes_after_scan"] == rep["scenes_after_esc"] == 1  # nothing left behind
