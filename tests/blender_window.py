"""A real Blender window for the add-on's tests: Debian's Blender 3.4 on an Xvfb display, the
legacy add-on installed, a script driving it and writing a JSON report."""

import json
import os
import shutil
import subprocess
import sys
import time
import zipfile
from contextlib import contextmanager
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@contextmanager
def virtual_display(base: int, size: str):
    """An Xvfb display (``size`` "WxH"), numbered from ``base`` so that tests side by side
    do not share one."""
    xvfb = shutil.which("Xvfb")
    if xvfb is None or shutil.which("blender") is None:
        pytest.skip("needs Xvfb and blender (apt-get install xvfb blender python3-numpy)")
    num = f":{base + os.getpid() % 9}"
    proc = subprocess.Popen([xvfb, num, "-screen", "0", f"{size}x24", "+extension", "GLX"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(1.0)
    try:
        yield num
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def run_in_window(tmp_path: Path, display: str, script: str, *args: str,
                  env_extra: dict | None = None) -> dict:
    """Install the legacy add-on, open Blender in ``display`` on a saved start file (that
    skips the splash screen), run ``tests/data/<script>`` with ``args``; its JSON report."""
    dist = tmp_path / "dist"
    subprocess.run([sys.executable, str(ROOT / "tools" / "build_addon.py"), "--out", str(dist),
                    "--legacy-only"], check=True, capture_output=True)
    with zipfile.ZipFile(next(dist.glob("apcg-legacy-*.zip"))) as z:
        z.extractall(tmp_path / "scripts" / "addons")
    start = tmp_path / "start.blend"
    subprocess.run(["blender", "-b", "--factory-startup", "--python-expr",
                    f"import bpy; bpy.ops.wm.save_as_mainfile(filepath={str(start)!r})"],
                   check=True, capture_output=True)
    report = tmp_path / "report.json"
    env = dict(os.environ, DISPLAY=display, BLENDER_USER_SCRIPTS=str(tmp_path / "scripts"),
               **(env_extra or {}))
    env.pop("PYTHONPATH", None)
    r = subprocess.run(["blender", "--factory-startup", "--enable-event-simulate", str(start),
                        "-P", str(ROOT / "tests" / "data" / script), "--", str(report), *args],
                       env=env, capture_output=True, text=True, timeout=300)
    assert report.exists(), (r.stdout[-2000:], r.stderr[-2000:])
    rep = json.loads(report.read_text())
    assert rep["error"] is None, rep["error"]
    return rep
