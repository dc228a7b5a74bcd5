"""A small Cycles render of an aircraft with its scanned cloud is not blank: the airframe and
the range-coloured points (near: yellow, far: blue) both show."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_cycles_render_shows_aircraft_and_cloud(tmp_path):
    pytest.importorskip("bpy")
    image = pytest.importorskip("matplotlib.image")
    out = tmp_path / "render.png"
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "render_example.py"), "-o", out,
                        "--size", "192", "108", "--samples", "4"], capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    rgb = image.imread(out)[..., :3].astype(np.float64)
    background = rgb[0, 0]
    differs = np.abs(rgb - background).max(axis=2) > 0.08
    assert 0.03 < differs.mean() < 0.8  # something in the frame, not everything
    r_, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    yellow = (r_ > b + 0.15) & (g > b + 0.1)
    blue = b > r_ + 0.15
    assert yellow.sum() >= 5 and blue.sum() >= 5  # both ends of the range colour ramp
