"""Results a user would not expect are said (stderr, exit 0), and only those."""

import csv
import json

from apcg_core.cli import main

WIDE = """types = ["Mavic 3", "A320neo"]
sampling = "random"
samples_per_type = 20
shard_size = 50
[ranges]
drone_range_m = [100.0, 17000.0]
"""


def test_a_drone_far_beyond_its_band_is_simulated_with_warnings(tmp_path, capsys):
    rc = main(["simulate", "--type", "Mavic 3", "--range-m", "17000", "--elevation-deg", "3",
               "-o", str(tmp_path / "far.ply")])
    out, err = capsys.readouterr()
    assert rc == 0 and (tmp_path / "far.ply").exists()
    points = json.loads(out)["points"]
    assert points < 10
    assert "Mavic 3 is a near-band type" in err and "100-600 m" in err
    assert ("is empty" in err) if points == 0 else (f"only {points} point" in err)


def test_an_ordinary_scan_says_nothing(tmp_path, capsys):
    rc = main(["simulate", "--type", "Mavic 3", "--range-m", "300", "--elevation-deg", "3",
               "--pitch-deg", "2", "-o", str(tmp_path / "near.ply")])
    out, err = capsys.readouterr()
    assert rc == 0 and json.loads(out)["points"] >= 10 and err == ""


def test_a_dataset_with_ranges_beyond_table1_counts_them(tmp_path, capsys):
    (tmp_path / "wide.toml").write_text(WIDE)
    rc = main(["dataset", "build", "--config", str(tmp_path / "wide.toml"), "-o",
               str(tmp_path / "ds"), "--no-progress"])
    out, err = capsys.readouterr()
    assert rc == 0
    with open(tmp_path / "ds" / "conditions.csv") as f:
        rows = list(csv.DictReader(f))
    drones = [float(r["range_m"]) for r in rows if r["type_name"] == "Mavic 3"]
    outside = sum(r > 600.0 for r in drones)
    assert 0 < outside < len(drones)  # the config's draws straddle the band's end
    assert json.loads(out)["samples_outside_table1_bands"] == outside
    assert f"{outside:,} of {len(rows):,} samples lie outside" in err
    rc = main(["dataset", "build", "--config", "demo", "-o", str(tmp_path / "demo"),
               "--no-progress"])
    assert rc == 0 and "warning" not in capsys.readouterr().err


def test_generated_empty_clouds_are_counted_and_said(tmp_path, capsys):
    # a hit threshold no logit reaches: every generated cloud is empty
    rc = main(["generate", "--type", "Mavic 3", "--range-m", "300", "--elevation-deg", "3",
               "--pitch-deg", "2", "--count", "3", "--tau", "1e9", "-o",
               str(tmp_path / "g.ply")])
    out, err = capsys.readouterr()
    assert rc == 0 and json.loads(out)["empty_clouds"] == 3
    assert "3 of 3 clouds are empty" in err


def test_the_window_check_finds_the_angles_of_every_vertex_in_bounded_passes(monkeypatch):
    """window_fit's extremes (found on the tangents, the arctangents taken of four points a
    row) are those of arctan2 over every vertex, to the last bits of a radian, also when the
    rows go through in many small passes (a mesh of many vertices) and for a point behind."""
    import numpy as np

    from apcg_core import plausibility
    from apcg_core.frames import body_to_observation_matrices, target_centres
    rng = np.random.default_rng(4)
    v = rng.normal(size=(500, 3)) * [20.0, 5.0, 18.0]
    table = np.column_stack([np.zeros(300), rng.uniform(150, 18000, 300),
                             rng.uniform(0.05, 0.07, 300), rng.uniform(-0.1, 0.1, (300, 3))])
    m = body_to_observation_matrices(table[:, 3], table[:, 4], table[:, 5])
    obs = np.einsum("nij,vj->nvi", m, v) + target_centres(table[:, 1], table[:, 2])[:, None]
    alpha = np.arctan2(obs[..., 0], obs[..., 2])
    beta = np.arctan2(obs[..., 1], np.hypot(obs[..., 0], obs[..., 2]))
    want = np.stack([alpha.min(1), alpha.max(1), beta.min(1), beta.max(1)], axis=1)
    got = plausibility._angle_extremes(obs)
    assert np.abs(got - want).max() < 1e-15
    behind = obs.copy()
    behind[0, 0] = [1.0, 0.0, -1.0]  # behind the sensor, to the right: 3 pi / 4
    a0 = np.arctan2(behind[0, :, 0], behind[0, :, 2])
    assert plausibility._angle_extremes(behind)[0, 1] == a0.max() > 2.0  # past pi / 2
    from apcg_core.lidar import LidarParams
    lidar = LidarParams()
    whole = plausibility.window_fit(lidar, lambda n: v, ["x"] * 300, table)
    monkeypatch.setattr(plausibility, "WINDOW_CHECK_POINTS", 1700)  # 3 rows a pass
    assert plausibility.window_fit(lidar, lambda n: v, ["x"] * 300, table) == whole
