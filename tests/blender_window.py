"""A real Blender window for the add-on's tests: Debian's Blender 3.4 on an Xvfb display, the
legacy add-on installed, a script driving it and writing a JSON report."""

import json
import os
import select
import shutil
import subprocess
import sys
import zipfile
from contextlib import contextmanager
from pathlib import Path

import pytest
from conftest import blender_or_skip

ROOT = Path(__file__).resolve().parents[1]


@contextmanager
def virtual_display(size: str):
    """An Xvfb display (``size`` "WxH") on a free number, yielded once Xvfb says it is ready
    (``-displayfd``: it writes its number when it accepts clients, however loaded the machine)."""
    blender_or_skip()
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        pytest.skip("needs Xvfb: apt-get install -y xvfb (the README's set-up)")
    read_end, write_end = os.pipe()
    proc = subprocess.Popen([xvfb, "-displayfd", str(write_end), "-screen", "0", f"{size}x24",
                             "+extension", "GLX"], pass_fds=(write_end,),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(write_end)
    try:
        ready, _, _ = select.select([read_end], [], [], 120)
        number = os.read(read_end, 64).decode().strip() if ready else ""
        assert number.isdigit(), f"Xvfb gave no display number in 120 s (exit {proc.poll()})"
        yield f":{number}"
    finally:
        os.close(read_end)
        proc.terminate()
        proc.wait(timeout=60)


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
