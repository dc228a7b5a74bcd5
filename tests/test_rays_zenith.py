"""Near the zenith a straight edge seen from the lidar rises far above its two ends (it is a
great-circle arc, and arcs bulge toward the pole): the box of cells cast must hold what the
edges reach, not only what the vertices do. A coarse box (12 triangles, 64 m edges) filling
the window at 3 km lost 4 to 12 of its 64 rows at 88.7-89 deg (a probe, stop 53)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from dataset_builder.rays import _arc_top
from tests.cli_run import run

# the user types these tests add stay out of the process's catalog (conftest.py)
pytestmark = pytest.mark.usefixtures("own_catalog")


@pytest.fixture
def slab(tmp_path, capsys):
    trimesh.creation.box(extents=(40.0, 64.0, 16.0)).export(tmp_path / "slab.obj")
    rc, _, err = run(["catalog", "add", tmp_path / "slab.obj", "--name", "zenith slab",
                      "--force"], capsys)
    assert rc == 0, err
    return "zenith slab"


@pytest.mark.parametrize("elevation", ["88.7", "89.0"])
def test_a_coarse_target_near_the_zenith_is_cast_whole(tmp_path, capsys, slab, elevation):
    rc, _, err = run(["simulate", "--type", slab, "--range-m", "3000", "--elevation-deg",
                      elevation, "-o", tmp_path / "z.npz"], capsys)
    assert rc == 0, err
    with np.load(tmp_path / "z.npz") as z:  # it fills the 256 x 64 window: every cell a hit
        assert len(z["xyz"]) == 256 * 64 and np.unique(z["cell_h"]).size == 64


def test_an_arcs_top_against_the_closed_form():
    """Two directions at one elevation, their azimuths dA apart: the arc's middle is at
    atan(tan e / cos(dA / 2)); an arc of their angular distance can reach no higher."""
    rng = np.random.default_rng(0)
    e = rng.uniform(-1.5, 1.5, 500)
    d_a = rng.uniform(0.0, 0.5, 500)
    length = np.arccos(np.sin(e) ** 2 + np.cos(e) ** 2 * np.cos(d_a))
    top = _arc_top(e, length)
    mid = np.where(e > 0, np.arctan(np.tan(e) / np.cos(d_a / 2)), e)
    assert np.allclose(top, mid, atol=1e-9) and (top >= e).all()
    # sampled along real arcs: never above the bound
    u = np.stack([np.cos(e), np.sin(e), np.zeros_like(e)], 1)
    v = np.stack([np.cos(e) * np.cos(d_a), np.sin(e), np.cos(e) * np.sin(d_a)], 1)
    for t in np.linspace(0, 1, 11):
        p = u * (1 - t) + v * t
        assert (np.arcsin(p[:, 1] / np.linalg.norm(p, axis=1)) <= top + 1e-12).all()


def test_an_empty_cloud_whose_parts_lie_outside_the_window_says_so(tmp_path, capsys):
    """Two 1 m cubes 90 m apart: at 3 km the window, centred between them, holds neither."""
    twin = trimesh.util.concatenate([trimesh.creation.box(extents=(1, 1, 1)),
                                     trimesh.creation.box(extents=(1, 1, 1)).apply_translation(
                                         (0.0, 90.0, 0.0))])  # 90 m of span apart
    twin.export(tmp_path / "twin.obj")
    rc, _, err = run(["catalog", "add", tmp_path / "twin.obj", "--name", "twin cubes",
                      "--force"], capsys)
    assert rc == 0, err
    rc, _, err = run(["simulate", "--type", "twin cubes", "--range-m", "3000",
                      "--elevation-deg", "3.5", "-o", tmp_path / "t.npz"], capsys)
    empty = [ln for ln in err.splitlines() if "is empty" in ln]
    assert rc == 0 and len(empty) == 1, err
    assert "parts lie outside the lidar's window" in empty[0] and "too small" not in empty[0]
