"""Scenes (issue 36): several targets in one window, occlusion, motion distortion, sequences.

Real embree, real catalog types, small scenes: the scanner is the simulator's own ray
machinery, so one target alone at azimuth 0 must be `apcg simulate` byte for byte."""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from apcg_core.cli import main
from apcg_core.errors import InputError
from apcg_core.frames import body_to_observation_matrix
from apcg_core.io import read_cloud
from apcg_core.lidar import DEG
from apcg_core.scene import flight_matrices, load_sequence, poses_from_angles, scene_from_dict
from apcg_core.scene.poses import angles_of_poses
from apcg_core.scene.trajectory import envelope_warnings
from dataset_builder.scene import SceneScanner

POSE = {"range_m": 4500.0, "elevation_deg": 3.5, "pitch_deg": 2.0, "yaw_deg": 30.0,
        "roll_deg": -3.0}
SIM_POSE = ["--range-m", "4500", "--elevation-deg", "3.5", "--pitch-deg", "2", "--yaw-deg",
            "30", "--roll-deg", "-3"]


def _toml(doc: dict) -> str:
    """A scene dict as TOML (tables and arrays of tables of scalars and sub-tables)."""
    out = []

    def scalar(v):
        return json.dumps(v) if isinstance(v, str) else repr(v).lower() \
            if isinstance(v, bool) else repr(v)

    def table(name, t, array=False):
        out.append(f"[[{name}]]" if array else f"[{name}]")
        subs = {}
        for k, v in t.items():
            if isinstance(v, dict):
                subs[k] = v
            else:
                out.append(f"{k} = {scalar(v)}")
        for k, v in subs.items():
            table(f"{name}.{k}", v)

    for name, v in doc.items():
        if isinstance(v, list):
            for t in v:
                table(name, t, array=True)
        else:
            table(name, v)
    return "\n".join(out) + "\n"


def _write_scene(path: Path, doc: dict) -> Path:
    path.write_text(_toml(doc))
    return path


def _scan(doc: dict, **kw):
    sc = SceneScanner(scene_from_dict(doc), **kw)
    try:
        return sc.scan(0)
    finally:
        sc.close()


def _cells(scan, instance=None) -> dict:
    m = np.ones(len(scan.cloud), bool) if instance is None else scan.instance == instance
    c = scan.cloud
    return {(int(w), int(h)): float(r) for w, h, r in zip(c.cell_w[m], c.cell_h[m],
                                                          c.range_m[m], strict=True)}


# --- one target: `apcg simulate` ---------------------------------------------------------------
@pytest.mark.parametrize("sensor", [[], ["--sensor", "1064nm-night", "--seed", "7"],
                                    ["--lidar", "half-cells"]],
                         ids=["ideal", "photons", "another-lidar"])
def test_one_target_at_azimuth_zero_is_simulate_byte_for_byte(tmp_path, capsys, sensor):
    scene = _write_scene(tmp_path / "one.toml", {"target": [{"type": "A320neo", **POSE}]})
    assert main(["scene", "scan", str(scene), "-o", str(tmp_path / "scene.npz"), *sensor]) == 0
    assert main(["simulate", "--type", "A320neo", *SIM_POSE, "-o", str(tmp_path / "sim.npz"),
                 *sensor]) == 0
    capsys.readouterr()
    got, want = np.load(tmp_path / "scene.npz"), np.load(tmp_path / "sim.npz")
    photons = "--sensor" in sensor
    keys = ["xyz", "range_m", "cell_w", "cell_h", "sample"] + (["label", "count"] if photons
                                                               else [])
    assert len(want["xyz"]) > 200
    for k in keys:
        assert got[k].dtype == want[k].dtype and got[k].tobytes() == want[k].tobytes(), k
    signal_pts = got["label"] == 1 if photons else np.ones(len(got["xyz"]), bool)
    assert (got["instance"][signal_pts] == 1).all() and (got["instance"][~signal_pts] == 0).all()
    assert set(got["type"][signal_pts]) == {"A320neo"}
    # the project's cloud reader takes it like any other NPZ cloud
    cloud, _ = read_cloud(tmp_path / "scene.npz")
    assert np.array_equal(cloud.xyz, got["xyz"])


def test_a_scene_files_lidar_table_is_the_lidar_unless_lidar_is_given(tmp_path, capsys):
    from apcg_core.lidar import load_lidar
    half = load_lidar("half-cells").to_dict()
    scene = _write_scene(tmp_path / "s.toml", {"lidar": half,
                                               "target": [{"type": "A320neo", **POSE}]})
    assert main(["scene", "scan", str(scene), "-o", str(tmp_path / "a.npz")]) == 0
    assert main(["scene", "scan", str(scene), "-o", str(tmp_path / "b.npz"), "--lidar",
                 "paper"]) == 0
    assert main(["simulate", "--type", "A320neo", *SIM_POSE, "-o", str(tmp_path / "c.npz"),
                 "--lidar", "half-cells"]) == 0
    capsys.readouterr()
    a, b, c = (np.load(tmp_path / f"{n}.npz") for n in "abc")
    assert np.array_equal(a["xyz"], c["xyz"]) and len(b["xyz"]) != len(a["xyz"])
    assert json.loads(str(a["meta"]))["lidar"] == half


def test_a_turned_window_is_the_simulated_cloud_turned(tmp_path):
    """A target at azimuth 20 deg, the window pointed at it: `apcg simulate`'s cloud (made in
    the target's own frame) turned by 20 deg about the vertical."""
    base = _scan({"target": [{"type": "A320neo", **POSE}]})
    turned = _scan({"target": [{"type": "A320neo", **POSE, "azimuth_deg": 20.0}]})
    assert np.array_equal(base.cloud.cell_w, turned.cloud.cell_w)
    assert np.array_equal(base.cloud.cell_h, turned.cloud.cell_h)
    # ranges to the bin: float64 rounding of a turned frame may move a float32 hit by ~1e-4 m
    assert np.abs(base.cloud.range_m - turned.cloud.range_m).max() < 1e-3
    a = 20 * DEG
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    assert np.abs(base.cloud.xyz @ rot.T - turned.cloud.xyz).max() < 1e-3


# --- occlusion ---------------------------------------------------------------------------------
CROSSING = {
    "pointing": {"azimuth_deg": 0.0, "elevation_deg": 3.5},
    "target": [{"type": "A320neo", "range_m": 6000.0, "azimuth_deg": 0.0,
                "elevation_deg": 3.5, "yaw_deg": 60.0},
               {"type": "737-800", "range_m": 6500.0, "azimuth_deg": 0.12,
                "elevation_deg": 3.52, "yaw_deg": -70.0}]}


def test_the_occluded_aircraft_loses_exactly_the_cells_the_nearer_one_covers():
    both = _scan(CROSSING)
    near = _scan({**CROSSING, "target": CROSSING["target"][:1]})
    far = _scan({**CROSSING, "target": CROSSING["target"][1:]})
    a, b = _cells(near), _cells(far)
    shared = set(a) & set(b)
    assert len(shared) > 50 and len(set(b) - shared) > 50  # partly behind, partly seen
    assert _cells(both, 1) == a
    assert _cells(both, 2) == {k: v for k, v in b.items() if k not in a}
    assert len(both.cloud) == len(set(a) | set(b))
    assert list(both.points_of()) == [len(a), len(set(b) - shared)]
    # the far one listed first: the same cloud, instance ids follow the list
    swapped = _scan({**CROSSING, "target": CROSSING["target"][::-1]})
    assert _cells(swapped, 2) == a and _cells(swapped, 1) == _cells(both, 2)


# --- motion distortion -------------------------------------------------------------------------
def _pass(scan_table=None) -> dict:
    doc = {"pointing": {"azimuth_deg": 0.0, "elevation_deg": 3.5},
           "target": [{"type": "A320neo", "range_m": 3000.0, "azimuth_deg": -0.1,
                       "elevation_deg": 3.5,
                       "trajectory": {"kind": "line", "speed_mps": 250.0,
                                      "heading_deg": 90.0}}]}
    if scan_table:
        doc["scan"] = scan_table
    return doc


def test_a_row_by_row_scan_skews_a_fast_pass_by_speed_times_row_time():
    """250 m/s across the line of sight, rows 1 ms apart from the top: each row of the cloud
    is shifted against a flash of the frame's start by the distance flown until it fired; the
    measured skew (shift per row) is speed x row time."""
    line_time = 1e-3
    rows = _scan(_pass({"pattern": "rows", "line_time_s": line_time}))
    flash = _scan(_pass())
    hs = sorted(set(rows.cloud.cell_h.tolist()) & set(flash.cloud.cell_h.tolist()))
    assert len(hs) > 20
    t, dx = [], []
    for h in hs:
        t.append((32 - 1 - h) * line_time)  # the top row (h = H/2 - 1) fires first
        dx.append(rows.cloud.xyz[rows.cloud.cell_h == h, 0].mean()
                  - flash.cloud.xyz[flash.cloud.cell_h == h, 0].mean())
    skew_per_row = np.polyfit(np.array(t) / line_time, dx, 1)[0]
    assert skew_per_row == pytest.approx(250.0 * line_time, rel=0.01)
    # a row's shift is the distance flown until it fired, to a fraction of a cell (0.2 m)
    assert np.abs(np.array(dx) - 250.0 * np.array(t)).max() < 0.5
    # bottom-up fires the bottom row first: the skew turns over
    up = _scan(_pass({"pattern": "rows", "line_time_s": line_time, "order": "bottom-up"}))
    top, bottom = max(hs), min(hs)
    shift = [up.cloud.xyz[up.cloud.cell_h == h, 0].mean()
             - flash.cloud.xyz[flash.cloud.cell_h == h, 0].mean() for h in (top, bottom)]
    assert shift[0] > shift[1] + 250 * line_time * (top - bottom) * 0.9


def test_a_static_scene_is_the_same_under_any_scan_pattern():
    still = {"target": [{"type": "A320neo", **POSE}]}
    flash = _scan(still)
    for pattern in ({"pattern": "rows", "line_time_s": 1e-3},
                    {"pattern": "columns", "line_time_s": 1e-4},
                    {"pattern": "cells", "cell_time_s": 1e-6, "order": "columns"}):
        other = _scan({**still, "scan": pattern})
        assert _cells(other) == _cells(flash)


@pytest.mark.parametrize("order", ["rows", "columns"])
def test_a_cell_by_cell_raster_draws_each_cell_where_the_target_was_when_it_fired(order):
    """[scan] pattern = "cells": every cell fires on its own, cell_time_s apart, in raster
    order. Each cell of a fast pass is the cell of a flash scan of the scene at that cell's
    own firing time, exactly; and the pass comes out skewed against a flash of the frame's
    start by the distance flown until each cell fired."""
    dt = 2e-6
    raster = _scan(_pass({"pattern": "cells", "cell_time_s": dt, "order": order}))
    got = _cells(raster)
    assert len(got) > 1000
    W, H = 256, 64
    rng = np.random.default_rng(3)
    picked = [list(got)[i] for i in rng.choice(len(got), 6, replace=False)]
    for w, h in picked:
        row, col = H // 2 - 1 - h, w + W // 2
        k = row * W + col if order == "rows" else col * H + row
        at = _scan({**_pass(), "sequence": {"start_s": k * dt}})
        assert _cells(at).get((w, h)) == got[(w, h)], (w, h, k)
    flash = _scan(_pass())
    # 250 m/s along +X: a cell's shift against the frame's start is 250 m/s x its firing time
    # (to the cells' size: the surface under a cell changes as the target moves)
    c, f = raster.cloud, flash.cloud
    t = np.where(order == "rows", (H // 2 - 1 - c.cell_h) * W + (c.cell_w + W // 2),
                 (c.cell_w + W // 2) * H + (H // 2 - 1 - c.cell_h)) * dt
    shift = c.xyz[:, 0].mean() - f.xyz[:, 0].mean()
    assert shift == pytest.approx(250.0 * t.mean(), abs=0.5)


def test_a_raster_needs_its_cell_time_and_a_known_order():
    for table, says in (({"pattern": "cells"}, "cell_time_s = None is not accepted"),
                        ({"pattern": "cells", "cell_time_s": -1.0}, "cell_time_s = -1.0"),
                        ({"pattern": "cells", "cell_time_s": 1e-6, "order": "diagonal"},
                         "order = 'diagonal' is not accepted"),
                        ({"pattern": "cells", "line_time_s": 1e-6}, "unknown key(s) line_time_s")):
        with pytest.raises(InputError, match=re.escape(says)):
            scene_from_dict({**_pass(), "scan": table})


# --- poses and trajectories --------------------------------------------------------------------
def test_pose_angles_round_trip_and_flight_attitude_matches_the_project_signs():
    ang = np.array([3000.0, 0.3, 0.05, 0.1, 0.2, -0.3])
    p, b = poses_from_angles(*ang)
    assert np.allclose(angles_of_poses(p, b)[0], ang, atol=1e-12)
    # flying straight at the lidar (heading 180 deg at azimuth 0) is SPEC section 2's zero
    # attitude; climbing is +pitch, a right bank is +roll, turning toward -X is -yaw
    assert np.allclose(flight_matrices(np.pi, 0.0, 0.0)[0], body_to_observation_matrix(0, 0, 0))
    assert np.allclose(flight_matrices(np.pi, 0.2, 0.0)[0],
                       body_to_observation_matrix(0.2, 0, 0))
    assert np.allclose(flight_matrices(np.pi, 0.0, 0.3)[0],
                       body_to_observation_matrix(0, 0, 0.3))
    assert np.allclose(flight_matrices(np.pi + 0.25, 0.0, 0.0)[0],
                       body_to_observation_matrix(0, -0.25, 0))


def test_generators_fly_what_they_say(tmp_path):
    start = {"type": "A320neo", "range_m": 5000.0, "azimuth_deg": 0.0, "elevation_deg": 3.0}
    doc = {"sequence": {"frames": 11, "frame_rate_hz": 10.0}, "target": [
        {**start, "trajectory": {"kind": "turn", "speed_mps": 120.0, "heading_deg": 0.0,
                                 "turn_rate_deg_s": 3.0}},
        {**start, "trajectory": {"kind": "climb", "speed_mps": 100.0, "heading_deg": 90.0,
                                 "climb_rate_mps": 10.0}},
        {**start, "type": "Mavic 3", "range_m": 300.0,
         "trajectory": {"kind": "hover", "drift_mps": 2.0, "drift_heading_deg": 90.0,
                        "heading_deg": 0.0}}]}
    scene = scene_from_dict(doc)
    t = scene.frame_times()
    turn, climb, hover = (tr.poses(t) for tr in scene.targets)
    v = np.diff(turn[0], axis=0) / 0.1
    assert np.allclose(np.linalg.norm(v, axis=1), 120.0, rtol=1e-3)
    heading = np.degrees(np.arctan2(turn[1][:, 0, 0], turn[1][:, 2, 0]))
    assert np.allclose(np.diff(heading), 0.3)  # 3 deg/s at 10 Hz
    bank = np.degrees(np.arctan(120.0 * 3 * DEG / 9.80665))
    roll = np.degrees(np.arcsin(turn[1][:, 1, 1]))  # left wing's rise = bank
    assert np.allclose(roll, bank)
    assert np.allclose(np.diff(climb[0][:, 1]), 1.0)  # 10 m/s up, 0.1 s a frame
    assert np.allclose(np.diff(hover[0][:, 0]), 0.2) and np.allclose(np.diff(hover[0][:, 2]), 0)
    # envelope: an airliner at 400 m/s, a light aircraft pulling 4.4 g, are warned about
    assert envelope_warnings("airliner_narrowbody", 400.0)
    assert envelope_warnings("light_GA", 60.0, np.radians(40.0))
    assert not envelope_warnings("airliner_narrowbody", 230.0, np.radians(3.0))


def test_a_csv_trajectory_interpolates_between_its_rows(tmp_path):
    rows = ["t_s,x_m,y_m,z_m,pitch_deg,yaw_deg,roll_deg"]
    for k in range(5):
        rows.append(f"{k * 0.5},{-60 + 40 * k},300.0,5000.0,0,{90 - k},0")
    (tmp_path / "track.csv").write_text("\n".join(rows) + "\n")
    doc = {"target": [{"type": "A320neo", "trajectory": {"kind": "csv", "file": "track.csv"}}],
           "sequence": {"frames": 5, "frame_rate_hz": 4.0}}
    scene = scene_from_dict(doc, base_dir=tmp_path)
    p, b = scene.targets[0].poses(np.array([0.25, 1.0]))
    assert np.allclose(p, [[-40.0, 300.0, 5000.0], [20.0, 300.0, 5000.0]])
    ang = angles_of_poses(p, b)
    assert np.degrees(ang[:, 4]) == pytest.approx([89.5, 88.0])
    # pointing follows the first target at the first frame
    assert scene.pointing_azimuth == pytest.approx(np.arctan2(-60.0, 5000.0))


# --- bad input: one line, nothing written ------------------------------------------------------
def _csv(tmp_path, times, name="track.csv"):
    rows = ["t_s,range_m,azimuth_deg,elevation_deg,pitch_deg,yaw_deg,roll_deg"]
    rows += [f"{t},5000,0,3.5,0,0,0" for t in times]
    (tmp_path / name).write_text("\n".join(rows) + "\n")
    return {"type": "A320neo", "trajectory": {"kind": "csv", "file": name}}


@pytest.mark.parametrize("case, says", [
    ("gap", "track.csv, line 5, column t_s (A): a gap of 2.5 s after 1 s"),
    ("backwards", "track.csv, line 5, column t_s (A): time 0.5 s does not increase"),
    ("outside", "target 2 (737-800) lies outside the lidar's window at t = 0 s"),
    ("unknown type", "target 2: unknown aircraft type 'A320-neo-XL'"),
    ("beyond the track", "target 1 (A320neo): scene time 2 s lies outside its trajectory"),
    ("frame too slow", "one frame's scan takes 0.063 s, longer than a frame at 20 Hz"),
])
def test_bad_scenes_get_one_named_line_and_nothing_is_written(tmp_path, capsys, case, says):
    doc = {"sequence": {"frames": 3, "frame_rate_hz": 1.0},
           "target": [{"type": "A320neo", **POSE}]}
    if case == "gap":
        doc["target"] = [_csv(tmp_path, [0, 0.5, 1.0, 3.5])]
    elif case == "backwards":
        doc["target"] = [_csv(tmp_path, [0, 0.5, 1.0, 0.5])]
    elif case == "outside":
        doc["target"].append({"type": "737-800", "range_m": 5000.0, "azimuth_deg": 3.0,
                              "elevation_deg": 3.5})
    elif case == "unknown type":
        doc["target"].append({"type": "A320-neo-XL", "range_m": 5000.0, "elevation_deg": 3.5})
    elif case == "beyond the track":
        doc["target"] = [_csv(tmp_path, [0, 0.5, 1.0, 1.5])]
    else:
        doc["sequence"] = {"frames": 3, "frame_rate_hz": 20.0}
        doc["scan"] = {"pattern": "rows", "line_time_s": 1e-3}
    scene = _write_scene(tmp_path / "bad.toml", doc)
    for cmd, out in (("scan", tmp_path / "out.npz"), ("sequence", tmp_path / "seq")):
        if case == "outside" and cmd == "sequence":
            continue  # a sequence refuses a target outside the window in every frame (below)
        assert main(["scene", cmd, str(scene), "-o", str(out), "--no-progress"][
            :None if cmd == "sequence" else -1]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], err
        assert not out.exists()


def test_a_sequence_refuses_a_target_outside_the_window_in_every_frame(tmp_path, capsys):
    doc = {"sequence": {"frames": 3, "frame_rate_hz": 1.0},
           "target": [{"type": "A320neo", **POSE},
                      {"type": "737-800", "range_m": 5000.0, "azimuth_deg": 3.0,
                       "elevation_deg": 3.5}]}
    scene = _write_scene(tmp_path / "bad.toml", doc)
    assert main(["scene", "sequence", str(scene), "-o", str(tmp_path / "seq"),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "target 2 (737-800) lies outside the lidar's window in every " \
                             "frame (3 frames)" in err[0]
    assert not (tmp_path / "seq").exists()


# --- sequences ---------------------------------------------------------------------------------
SEQUENCE = {
    "pointing": {"azimuth_deg": 0.0, "elevation_deg": 3.5},
    "scan": {"pattern": "rows", "line_time_s": 5e-4},
    "sequence": {"frames": 12, "frame_rate_hz": 10.0},
    "target": [
        {"type": "A320neo", "range_m": 6000.0, "azimuth_deg": -0.3, "elevation_deg": 3.5,
         "trajectory": {"kind": "line", "speed_mps": 200.0, "heading_deg": 90.0}},
        {"type": "F-16C Fighting Falcon", "range_m": 5000.0, "azimuth_deg": 0.2,
         "elevation_deg": 3.45,
         "trajectory": {"kind": "turn", "speed_mps": 250.0, "heading_deg": -90.0,
                        "turn_rate_deg_s": 5.0}},
        {"type": "UH-60 Black Hawk", "range_m": 7000.0, "azimuth_deg": 0.0,
         "elevation_deg": 3.6,
         "trajectory": {"kind": "hover", "drift_mps": 3.0, "drift_heading_deg": 45.0,
                        "heading_deg": 120.0}}]}


def _files(directory: Path) -> dict:
    return {str(p.relative_to(directory)): p.read_bytes()
            for p in sorted(directory.rglob("*")) if p.is_file()}


def _sequence_cmd(scene: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "apcg_core.cli", "scene", "sequence", str(scene), "-o",
            str(out), "--no-progress", *extra]


def _reference_sequence(tmp_path_factory, doc: dict):
    """A scene file of ``doc`` and its sequence built in this process: (scene, files, dir)."""
    d = tmp_path_factory.mktemp("seq")
    scene = _write_scene(d / "scene.toml", doc)
    assert main(["scene", "sequence", str(scene), "-o", str(d / "one"), "--no-progress"]) == 0
    return scene, _files(d / "one"), d / "one"


def _stop_mid_frame(scene: Path, out: Path, hold, sig) -> tuple[int, str]:
    """`apcg scene sequence` held after its first frame is computed, sent ``sig``: (exit
    code, stderr)."""
    point = "scene.frame-computed"
    proc = subprocess.Popen(_sequence_cmd(scene, out), env=hold.env(point),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        pid = hold.wait(point, proc)
        os.kill(pid, sig)
        hold.release(point)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, err


def _sequence_files(scene: Path, out: Path, *extra: str) -> dict:
    """The files of `apcg scene sequence SCENE -o OUT EXTRA` run in a process of its own."""
    r = subprocess.run(_sequence_cmd(scene, out, *extra), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return _files(out)


@pytest.fixture(scope="module")
def sequence_reference(tmp_path_factory):
    return _reference_sequence(tmp_path_factory, SEQUENCE)


def test_a_sequence_reads_back_with_labels_poses_and_tracks(sequence_reference):
    scene_path, files, out = sequence_reference
    assert sorted(f for f in files if not f.startswith("frames/")) == [
        "manifest.json", "poses.csv", "sequence.json"]
    seq = load_sequence(out)
    assert len(seq) == 12 and seq.complete
    assert [t["type"] for t in seq.header["tracks"]] == ["A320neo", "F-16C Fighting Falcon",
                                                         "UH-60 Black Hawk"]
    scene = scene_from_dict(SEQUENCE)
    tracks = seq.tracks()
    assert sorted(tracks) == [1, 2, 3]
    for tid, target in zip((1, 2, 3), scene.targets, strict=True):
        p, b = target.poses(scene.frame_times())
        assert np.array_equal(tracks[tid]["position"], p)
        assert np.array_equal(tracks[tid]["rotation"], b)
    # the jets fly out of the window (1 deg wide: 100 m at 6 km) within the second; the
    # hovering helicopter stays: seen frames have points, the others none
    inside = np.array([f.in_window for f in seq])  # (frames, tracks)
    points = np.stack([tracks[t]["points"] for t in (1, 2, 3)], 1)
    assert (points[~inside] == 0).all() and (points[inside] > 0).all()
    assert inside[0].all() and not inside[-1, :2].any() and inside[:, 2].all()
    f = seq.frame(2)
    assert f.t_s == pytest.approx(0.2) and set(np.unique(f.instance)) == {1, 2, 3}
    for tid in (1, 2, 3):
        assert set(f.type[f.instance == tid]) == {tracks[tid]["type"]}
        # a target's points lie around its position (within its size and the rows' motion)
        assert np.linalg.norm(f.points_of(tid).mean(0) - f.position[tid - 1]) < 25.0
    csv = (out / "poses.csv").read_text().splitlines()
    assert csv[0].startswith("frame,t_s,track_id,type,x_m,y_m,z_m,r00") and len(csv) == 37


@pytest.mark.parametrize("how", ["SIGKILL", "Ctrl-C"])
def test_a_sequence_stopped_mid_frame_resumes_to_the_same_bytes(sequence_reference, tmp_path,
                                                                hold, how):
    scene, want, _ = sequence_reference
    out = tmp_path / "seq"
    rc, err = _stop_mid_frame(scene, out, hold, signal.SIGKILL if how == "SIGKILL"
                              else signal.SIGINT)
    assert not (out / "manifest.json").exists()
    if how == "Ctrl-C":
        lines = err.strip().splitlines()
        assert rc == 130 and len(lines) == 1, err
        assert lines[0].startswith("apcg scene: interrupted: 0 of 12 frames are done in")
        assert not [p for p in out.rglob("*.part*")]  # nothing half-written left
    assert _sequence_files(scene, out) == want


def test_a_sequence_is_the_same_bytes_on_a_local_pool(sequence_reference, tmp_path):
    scene, want, _ = sequence_reference
    assert _sequence_files(scene, tmp_path / "seq", "--workers", "2") == want


def test_a_sequence_on_a_running_dask_cluster_is_the_same_bytes(sequence_reference, tmp_path):
    """`--engine dask --address`: a scheduler and a worker started apart (the docs' recipe),
    the worker in another directory; the engine first checks that it sees sequence.json."""
    from test_build_engine import _dask_cluster
    scene, want, _ = sequence_reference
    with _dask_cluster(tmp_path, dict(os.environ)) as (address, _):
        got = _sequence_files(scene, tmp_path / "seq", "--engine", "dask", "--address",
                              address)
    assert got == want


def test_a_sequence_of_another_scene_is_not_mixed_into_a_directory(sequence_reference,
                                                                   tmp_path, capsys):
    scene, _, out = sequence_reference
    other = _write_scene(tmp_path / "other.toml",
                         {**SEQUENCE, "sequence": {"frames": 4, "frame_rate_hz": 10.0}})
    assert main(["scene", "sequence", str(other), "-o", str(out), "--no-progress"]) == 2
    assert "already holds a different sequence" in capsys.readouterr().err


def test_scene_tables_are_checked_by_name():
    with pytest.raises(InputError, match=r"unknown key\(s\) colour; accepted: type, range_m"):
        scene_from_dict({"target": [{"type": "A320neo", **POSE, "colour": "red"}]})
    with pytest.raises(InputError, match="trajectory kind 'zigzag' is unknown; accepted: line"):
        scene_from_dict({"target": [{"type": "A320neo", "range_m": 5000.0,
                                     "elevation_deg": 3.5, "trajectory": {"kind": "zigzag"}}]})
    with pytest.raises(InputError, match="yaw_deg and roll_deg come from its line trajectory"):
        scene_from_dict({"target": [{"type": "A320neo", **POSE, "trajectory": {
            "kind": "line", "speed_mps": 100.0, "heading_deg": 0.0}}]})
    with pytest.raises(InputError, match="pattern = 'spiral' is unknown"):
        scene_from_dict({"target": [{"type": "A320neo", **POSE}],
                         "scan": {"pattern": "spiral"}})
    with pytest.raises(InputError, match="no \\[\\[target\\]\\] table"):
        scene_from_dict({"pointing": {"azimuth_deg": 0.0}})


def test_the_quick_window_screen_never_misses_a_target_the_boxes_see():
    from dataset_builder.scene import sphere_presence, window_presence
    sc = SceneScanner(scene_from_dict(SEQUENCE))
    try:
        quick = sphere_presence(sc, range(12))
        exact = window_presence(sc, range(12))
    finally:
        sc.close()
    assert exact.any() and not exact.all()  # the jets leave: both answers occur
    assert (quick | ~exact).all()


def test_photons_over_a_crossing_label_each_signal_point_with_the_target_it_came_from():
    from apcg_core.sensor import load_sensor, sensor_from_table
    doc = {**CROSSING, "pointing": {**CROSSING["pointing"], "range_m": 6250.0}}
    ideal = _scan(doc, supersample=2)  # the same sub-rays, the nearest kept per cell
    night = load_sensor("1064nm-night")
    # the preset's 100 m gate holds one of the two (500 m apart); one of 1 km holds both, a
    # dead time longer than it keeps one event per pulse
    wide = sensor_from_table({**night.to_dict(), "gate_m": 1000.0, "dead_time_ns": 7000.0})
    alone = _scan(CROSSING, supersample=2, sensor=night, seed=3)
    assert set(alone.instance[alone.cloud.label == 1]) == {1}  # gated on the first target
    photons = _scan(doc, supersample=2, sensor=wide, seed=3)
    c = photons.cloud
    sig = c.label == 1
    assert sig.sum() > 300 and (photons.instance[~sig] == 0).all()
    owner = {k: i for i in (1, 2) for k in _cells(ideal, i)}
    got = [owner.get((int(w), int(h))) for w, h in zip(c.cell_w[sig], c.cell_h[sig],
                                                        strict=True)]
    agree = np.mean([g == i for g, i in zip(got, photons.instance[sig], strict=True)])
    assert agree > 0.98  # the rest: cells split between the two at an edge
    assert set(photons.instance[sig]) == {1, 2}
    assert (np.abs(c.range_m[sig] - 6250.0) < 500.0).all()


def test_a_sequences_first_frame_with_photons_is_the_scan_of_the_scene(tmp_path, capsys):
    doc = {**SEQUENCE, "sequence": {"frames": 2, "frame_rate_hz": 10.0}}
    scene = _write_scene(tmp_path / "s.toml", doc)
    opts = ["--sensor", "1064nm-night", "--seed", "5", "--supersample", "1"]
    assert main(["scene", "scan", str(scene), "-o", str(tmp_path / "a.npz"), *opts]) == 0
    assert main(["scene", "sequence", str(scene), "-o", str(tmp_path / "seq"), *opts,
                 "--no-progress"]) == 0
    capsys.readouterr()
    a = np.load(tmp_path / "a.npz")
    f0 = np.load(tmp_path / "seq" / "frames" / "000000.npz")
    for k in ("xyz", "range_m", "cell_w", "cell_h", "label", "count", "instance", "type"):
        assert a[k].tobytes() == f0[k].tobytes(), k


def test_a_trajectory_beyond_its_type_is_warned_about(tmp_path, capsys):
    doc = {"target": [{"type": "A320neo", "range_m": 5000.0, "elevation_deg": 3.5,
                       "trajectory": {"kind": "line", "speed_mps": 400.0,
                                      "heading_deg": 180.0}}]}
    scene = _write_scene(tmp_path / "fast.toml", doc)
    assert main(["scene", "scan", str(scene), "-o", str(tmp_path / "a.npz")]) == 0
    err = capsys.readouterr().err
    assert "warning: " in err and "speed 400 m/s exceeds what a airliner_narrowbody flies" in err


def test_frames_without_a_header_are_never_taken_in(sequence_reference, tmp_path, capsys):
    scene, _, ref = sequence_reference
    shutil.copytree(ref / "frames", tmp_path / "seq" / "frames")
    assert main(["scene", "sequence", str(scene), "-o", str(tmp_path / "seq"),
                 "--no-progress"]) == 2
    assert "frame file(s) (000000.npz, ...) but" in capsys.readouterr().err


@pytest.mark.parametrize("damage", ["cut", "other scene"])
def test_a_damaged_or_foreign_frame_is_made_again(sequence_reference, tmp_path, capsys,
                                                  damage):
    scene, want, ref = sequence_reference
    out = tmp_path / "seq"
    shutil.copytree(ref, out)
    (out / "manifest.json").unlink()  # a sequence still being made
    victim = out / "frames" / "000002.npz"
    if damage == "cut":
        victim.write_bytes(victim.read_bytes()[:500])
    else:  # the same frame of a scene whose jet flies 50 m further out
        doc = json.loads(json.dumps(SEQUENCE))
        doc["target"][0]["range_m"] = doc["target"][0].get("range_m", 6000.0) + 50.0
        other = _write_scene(tmp_path / "other.toml", doc)
        assert main(["scene", "sequence", str(other), "-o", str(tmp_path / "o"),
                     "--no-progress"]) == 0
        shutil.copy(tmp_path / "o" / "frames" / "000002.npz", victim)
    capsys.readouterr()
    assert main(["scene", "sequence", str(scene), "-o", str(out), "--no-progress"]) == 0
    assert f"{victim} is not this sequence's" in capsys.readouterr().err
    assert _files(out) == want


@pytest.mark.parametrize("change", [{"speed_mps": 1e308}, {"speed_mps": 1e7},
                                    {"start_s": 1e300}])
def test_a_target_carried_beyond_any_range_is_refused_by_frame(tmp_path, capsys, change):
    doc = json.loads(json.dumps(SEQUENCE))
    doc["target"] = doc["target"][:1]
    if "start_s" in change:
        doc["sequence"]["start_s"] = change["start_s"]
    else:
        doc["target"][0]["trajectory"]["speed_mps"] = change["speed_mps"]
        doc["target"][0]["trajectory"]["heading_deg"] = 0.0  # straight away from the lidar
    scene = _write_scene(tmp_path / "far.toml", doc)
    for cmd, out in (("sequence", tmp_path / "seq"), ("scan", tmp_path / "scan.npz")):
        extra = ["--no-progress"] if cmd == "sequence" else []
        assert main(["scene", cmd, str(scene), "-o", str(out), *extra]) == 2, \
            capsys.readouterr().err
        err = capsys.readouterr().err
        if cmd == "sequence" and "start_s" not in change:  # (else the window's check may come
            # first: refused all the same)
            assert "accepted: a range <= 1e+06 m at every frame" in err, err
        assert not out.exists()
