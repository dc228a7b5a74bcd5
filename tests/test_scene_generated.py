"""Generated targets in scenes (issue 36, part 5): a target's cells drawn by a model (the
shipped APCG+) instead of the simulator, composited with the others by range.

Real parts at small sizes: the shipped model (onnxruntime), real embree for the simulated
targets, real processes for the resumed and distributed sequences."""

import json
import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
from test_scene import (
    _cells,
    _reference_sequence,
    _scan,
    _sequence_files,
    _stop_mid_frame,
    _write_scene,
)

from apcg_core.cli import main
from apcg_core.families import load_model
from apcg_core.lidar import DEG
from apcg_core.scene import load_sequence

POSE = {"range_m": 6000.0, "elevation_deg": 3.5, "pitch_deg": 2.0, "yaw_deg": 30.0,
        "roll_deg": -3.0}
GEN_POSE = ["--range-m", "6000", "--elevation-deg", "3.5", "--pitch-deg", "2", "--yaw-deg",
            "30", "--roll-deg", "-3"]
CLOUD = ("xyz", "range_m", "cell_w", "cell_h", "sample")


def _same(a, b, keys=CLOUD) -> None:
    for k in keys:
        assert a[k].dtype == b[k].dtype and a[k].tobytes() == b[k].tobytes(), k


# --- one generated target: `apcg generate` -------------------------------------------------------
def test_a_generated_target_alone_at_azimuth_zero_is_apcg_generate(tmp_path, capsys):
    scene = _write_scene(tmp_path / "one.toml",
                         {"target": [{"type": "A320neo", **POSE, "generator": "default"}]})
    assert main(["scene", "scan", str(scene), "-o", str(tmp_path / "scene.npz")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert main(["generate", "--type", "A320neo", *GEN_POSE, "-o",
                 str(tmp_path / "gen.npz")]) == 0
    capsys.readouterr()
    got, want = np.load(tmp_path / "scene.npz"), np.load(tmp_path / "gen.npz")
    assert len(want["xyz"]) > 200
    _same(got, want)
    assert (got["instance"] == 1).all() and list(got["generated"]) == [True]
    assert summary["generator"]["1"]["generated_frames"] == 1
    assert summary["generator"]["1"]["fallback_frames"] == []
    # the simulator's cloud of the same pose is another one (the model is not a copy of it)
    sim = _scan({"target": [{"type": "A320neo", **POSE}]})
    assert _cells(sim) != {(int(w), int(h)): float(r) for w, h, r in
                           zip(got["cell_w"], got["cell_h"], got["range_m"], strict=True)}
    # --generator on the command line draws every target without its own key: the same file
    plain = _write_scene(tmp_path / "plain.toml", {"target": [{"type": "A320neo", **POSE}]})
    assert main(["scene", "scan", str(plain), "-o", str(tmp_path / "cli.npz"),
                 "--generator", "default"]) == 0
    capsys.readouterr()
    cli = np.load(tmp_path / "cli.npz")
    _same(cli, got, [*CLOUD, "generated", "meta"])
    # and generator = false keeps a target simulated whatever --generator says
    off = _write_scene(tmp_path / "off.toml",
                       {"target": [{"type": "A320neo", **POSE, "generator": False}]})
    assert main(["scene", "scan", str(off), "-o", str(tmp_path / "off.npz"),
                 "--generator", "default"]) == 0
    capsys.readouterr()
    off_cells = np.load(tmp_path / "off.npz")
    assert off_cells["cell_w"].tobytes() == sim.cloud.cell_w.tobytes()
    assert "generated" not in off_cells.files  # a scene that generates nothing: as before


def test_an_off_centre_generated_target_is_its_own_line_of_sight_cloud_moved_by_whole_cells():
    """Off the window's centre the model draws the target on its own line of sight (the pose
    relative to it, at its own elevation) and its cells move by the offset rounded to whole
    cells (SPEC section 10)."""
    az, el = 0.061, 3.527  # 15.25 and 3.55 cells off: 15 and 4 whole cells
    scan = _scan({"pointing": {"azimuth_deg": 0.0, "elevation_deg": 3.5},
                  "target": [{"type": "A320neo", **POSE, "azimuth_deg": az,
                              "elevation_deg": el, "generator": "default"}]})
    model = load_model()
    own = model.generate(model.condition("A320neo", 6000.0, el * DEG, 2 * DEG, 30 * DEG,
                                         -3 * DEG)).cloud
    dw, dh = 15, 4
    assert round(az / 0.004) == dw and round((el - 3.5) / 0.0076) == dh
    want = {(int(w) + dw, int(h) + dh): float(r)
            for w, h, r in zip(own.cell_w, own.cell_h, own.range_m, strict=True)}
    assert len(want) > 200 and _cells(scan) == want
    # the points sit at the scene's cell centres (window centre: azimuth 0, elevation 3.5)
    c = scan.cloud
    alpha = np.arctan2(c.xyz[:, 0], c.xyz[:, 2])
    assert np.abs(alpha - c.cell_w * 0.004 * DEG).max() < 1e-9


def test_a_static_generated_target_is_the_same_under_any_scan_pattern():
    """Every row (or column) group of a still target has the same pose: one drawing, each
    group cut from it, the flash's cells."""
    still = {"pointing": {"azimuth_deg": 0.0, "elevation_deg": 3.5},
             "target": [{"type": "A320neo", **POSE, "azimuth_deg": 0.03,
                         "generator": "default"}]}
    flash = _scan(still)
    assert len(flash.cloud) > 200
    for pattern in ({"pattern": "rows", "line_time_s": 1e-3},
                    {"pattern": "columns", "line_time_s": 1e-4}):
        assert _cells(_scan({**still, "scan": pattern})) == _cells(flash)


def test_a_moving_generated_target_is_drawn_row_by_row_where_it_was_when_each_row_fired():
    """Rows 1 ms apart: each row's cells are the model's drawing of the target at the pose it
    had when that row fired (its offset in whole cells), so the generated cloud carries the
    motion distortion as the simulated one does."""
    from apcg_core.scene.poses import angles_of_poses
    from dataset_builder.scene import SceneScanner
    doc = {"pointing": {"azimuth_deg": 0.0, "elevation_deg": 3.5},
           "scan": {"pattern": "rows", "line_time_s": 1e-3},
           "target": [{"type": "A320neo", "range_m": 5000.0, "azimuth_deg": -0.05,
                       "elevation_deg": 3.5, "generator": "default",
                       "trajectory": {"kind": "line", "speed_mps": 150.0,
                                      "heading_deg": 150.0, "climb_deg": 3.0}}]}
    from apcg_core.scene import scene_from_dict
    sc = SceneScanner(scene_from_dict(doc))
    try:
        scan = sc.scan(0)
        g, target = sc.groups, sc.scene.targets[0]
    finally:
        sc.close()
    model = load_model()
    got = _cells(scan)
    rows = sorted({h for _, h in got})
    assert len(rows) > 10
    shifts = []
    for h in rows:
        row = int(np.flatnonzero((g.h_lo <= h) & (g.h_hi >= h))[0])
        ang = angles_of_poses(*target.poses(g.time_s[row]))[0]
        own = model.generate(model.condition("A320neo", ang[0], ang[2], *ang[3:])).cloud
        dw = int(np.rint(ang[1] / (0.004 * DEG)))
        dh = int(np.rint((ang[2] - 3.5 * DEG) / (0.0076 * DEG)))
        want = {(int(w) + dw, int(hh) + dh): float(r) for w, hh, r in
                zip(own.cell_w, own.cell_h, own.range_m, strict=True) if int(hh) + dh == h}
        assert {k: v for k, v in got.items() if k[1] == h} == want, h
        shifts.append(dw)
    assert len(set(shifts)) > 1  # the target moved by whole cells while the rows fired


# --- nearest wins ------------------------------------------------------------------------------
CROSSING = {
    "pointing": {"azimuth_deg": 0.0, "elevation_deg": 3.5},
    "target": [{"type": "A320neo", "range_m": 6000.0, "azimuth_deg": 0.0,
                "elevation_deg": 3.5, "pitch_deg": 2.0, "yaw_deg": 55.0,
                "generator": "default"},
               {"type": "737-800", "range_m": 6500.0, "azimuth_deg": 0.12,
                "elevation_deg": 3.52, "yaw_deg": -70.0}]}


@pytest.mark.parametrize("generated", ["near", "far"])
def test_a_generated_target_hides_exactly_the_cells_it_covers(generated):
    """Nearest surface per cell over simulated and generated targets alike: the far one
    keeps exactly its own cells that the near one does not cover."""
    near_t, far_t = (dict(t) for t in CROSSING["target"])
    if generated == "far":  # the simulated A320neo in front of a generated 737-800
        near_t.pop("generator")
        far_t.update(pitch_deg=3.0, yaw_deg=-50.0, generator="default")
    doc = {**CROSSING, "target": [near_t, far_t]}
    both = _scan(doc)
    near = _scan({**doc, "target": [near_t]})
    far = _scan({**doc, "target": [far_t]})
    a, b = _cells(near), _cells(far)
    shared = set(a) & set(b)
    assert len(shared) > 50 and len(set(b) - shared) > 50  # partly behind, partly seen
    assert _cells(both, 1) == a
    assert _cells(both, 2) == {k: v for k, v in b.items() if k not in a}
    assert list(both.points_of()) == [len(a), len(set(b) - shared)]
    assert list(both.generated) == ([True, False] if generated == "near" else [False, True])


# --- the fallback rule -------------------------------------------------------------------------
def _yaw_track(tmp_path, yaws, name="turning.csv") -> dict:
    """A target whose yaw (relative to its line of sight) is ``yaws`` at frames 0, 1, ..."""
    rows = ["t_s,range_m,azimuth_deg,elevation_deg,pitch_deg,yaw_deg,roll_deg"]
    rows += [f"{0.1 * k:.1f},6000,0,3.5,2,{y},0" for k, y in enumerate(yaws)]
    (tmp_path / name).write_text("\n".join(rows) + "\n")
    return {"type": "A320neo", "trajectory": {"kind": "csv", "file": name}}


def test_a_pose_the_model_cannot_draw_is_simulated_counted_and_warned(tmp_path, capsys):
    """The shipped model draws yaw -60..60 deg only: frames beyond are simulated for that
    target, said in one warning line and counted in the manifest; the rest is generated."""
    doc = {"pointing": {"azimuth_deg": 0.0, "elevation_deg": 3.5},
           "sequence": {"frames": 4, "frame_rate_hz": 10.0},
           "target": [_yaw_track(tmp_path, [40, 55, 65, 75])]}
    sim = _write_scene(tmp_path / "sim.toml", doc)
    gen = _write_scene(tmp_path / "gen.toml", {**doc, "target": [
        {**doc["target"][0], "generator": "default"}]})
    assert main(["scene", "sequence", str(sim), "-o", str(tmp_path / "s"),
                 "--no-progress"]) == 0
    assert capsys.readouterr().err == ""
    assert main(["scene", "sequence", str(gen), "-o", str(tmp_path / "g"),
                 "--no-progress"]) == 0
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("apcg scene: warning: the generator cannot draw every pose")
    assert "target 1 (A320neo) in 2 of 4 frames (first: frame 2: yaw_deg 65 deg outside " \
           "the model's -60 .. 60 deg)" in lines[0]
    manifest = json.loads((tmp_path / "g" / "manifest.json").read_text())
    assert manifest["generator"]["1"]["generated_frames"] == 2
    assert manifest["generator"]["1"]["fallback_frames"] == [2, 3]
    assert json.loads(out)["generator"] == manifest["generator"]
    s, g = load_sequence(tmp_path / "s"), load_sequence(tmp_path / "g")
    assert [bool(f.generated[0]) for f in g] == [True, True, False, False]
    assert g.frame(2).meta["fallback"] == {"1": "yaw_deg 65 deg outside the model's -60 .. "
                                                "60 deg"}
    for k in range(4):  # the fallback frames are the simulator's, the others the model's
        same = [np.array_equal(getattr(s.frame(k), a), getattr(g.frame(k), a))
                for a in ("xyz", "range_m", "cell_w", "cell_h")]
        assert all(same) == (k >= 2), k
    # a scan says the same of its one frame
    scan_doc = {**doc, "target": [{"type": "A320neo", **POSE, "yaw_deg": 75.0,
                                   "generator": "default"}]}
    scene = _write_scene(tmp_path / "scan.toml", scan_doc)
    assert main(["scene", "scan", str(scene), "-o", str(tmp_path / "f.npz")]) == 0
    out, err = capsys.readouterr()
    assert len(err.strip().splitlines()) == 1 and "in 1 of 1 frames" in err
    assert json.loads(out)["generator"]["1"]["fallback_frames"] == [0]
    assert list(np.load(tmp_path / "f.npz")["generated"]) == [False]


# --- bad input: one line, nothing written -----------------------------------------------------
def _renamed_model(tmp_path) -> Path:
    """A copy of the shipped model that knows no 'A320neo' (the type renamed)."""
    from apcg_core.families import default_model_dir
    d = tmp_path / "model"
    shutil.copytree(default_model_dir(), d)
    meta = json.loads((d / "model.json").read_text())
    for t in meta["types"]:
        if t["name"] == "A320neo":
            t["name"] = "A320neo-renamed"
    (d / "model.json").write_text(json.dumps(meta))
    return d


@pytest.mark.parametrize("case, says", [
    ("number", "target 1 (A320neo): generator = 3 is not accepted: \"default\" (the shipped "
               "model), a model directory"),
    ("true", "target 1 (A320neo): generator = True is not accepted"),
    ("missing", "target 1 (A320neo): generator = 'no-such-model': model directory "),
    ("cli missing", "--generator = 'no-such-model': model directory "),
    ("unknown type", "target 1 (A320neo): generator: type 'A320neo' is not one model "),
    ("sensor", "target 1 (A320neo): a generated target cannot feed the photon stage"),
])
def test_bad_generators_get_one_named_line_and_nothing_is_written(tmp_path, capsys, case,
                                                                  says):
    target = {"type": "A320neo", **POSE}
    extra = []
    if case == "number":
        target["generator"] = 3
    elif case == "true":
        target["generator"] = True
    elif case == "missing":
        target["generator"] = "no-such-model"
    elif case == "cli missing":
        extra = ["--generator", "no-such-model"]
    elif case == "unknown type":
        target["generator"] = str(_renamed_model(tmp_path))
    else:
        target["generator"] = "default"
        extra = ["--sensor", "1064nm-night"]
    scene = _write_scene(tmp_path / "bad.toml", {"target": [target]})
    for cmd, out in (("scan", tmp_path / "out.npz"), ("sequence", tmp_path / "seq")):
        argv = ["scene", cmd, str(scene), "-o", str(out), *extra]
        assert main(argv + (["--no-progress"] if cmd == "sequence" else [])) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], err
        assert not out.exists()


# --- determinism: resumed, a pool, Dask --------------------------------------------------------
SEQUENCE = {
    "pointing": {"azimuth_deg": 0.0, "elevation_deg": 3.5},
    "scan": {"pattern": "rows", "line_time_s": 5e-4},
    "sequence": {"frames": 10, "frame_rate_hz": 10.0},
    "target": [
        {"type": "A320neo", "range_m": 6000.0, "azimuth_deg": -0.1, "elevation_deg": 3.5,
         "generator": "default",
         "trajectory": {"kind": "line", "speed_mps": 120.0, "heading_deg": 170.0,
                        "climb_deg": 3.0}},
        {"type": "F-16C Fighting Falcon", "range_m": 5000.0, "azimuth_deg": 0.1,
         "elevation_deg": 3.45, "generator": "default",
         "trajectory": {"kind": "line", "speed_mps": 150.0, "heading_deg": -170.0,
                        "climb_deg": 2.0}},
        {"type": "UH-60 Black Hawk", "range_m": 7000.0, "azimuth_deg": 0.0,
         "elevation_deg": 3.6,
         "trajectory": {"kind": "hover", "drift_mps": 3.0, "drift_heading_deg": 45.0,
                        "heading_deg": 120.0}}]}


@pytest.fixture(scope="module")
def generated_reference(tmp_path_factory):
    return _reference_sequence(tmp_path_factory, SEQUENCE)


def test_a_generated_sequence_draws_its_targets_and_reads_back(generated_reference):
    _, files, out = generated_reference
    seq = load_sequence(out)
    gen = np.array([f.generated for f in seq])
    inside = np.array([f.in_window for f in seq])
    assert gen[:, :2].all() and not gen[:, 2].any()  # every pose inside the model's space
    points = np.array([f.points for f in seq])
    assert (points[inside] > 0).all() and inside[:, :2].sum() >= 10
    manifest = json.loads(files["manifest.json"])
    assert manifest["generator"]["1"]["fallback_frames"] == []
    assert manifest["generator"]["2"]["generated_frames"] == int(inside[:, 1].sum())
    assert "3" not in manifest["generator"]
    # the rows scan moves a generated target too: each row group drawn at its own time
    f = seq.frame(3)
    assert np.linalg.norm(f.points_of(1).mean(0) - f.position[0]) < 25.0


def test_a_generated_sequence_resumes_after_a_kill_to_the_same_bytes(generated_reference,
                                                                     tmp_path, hold):
    scene, want, _ = generated_reference
    out = tmp_path / "seq"
    _stop_mid_frame(scene, out, hold, signal.SIGKILL)
    assert not (out / "manifest.json").exists()
    assert _sequence_files(scene, out) == want


def test_a_generated_sequence_is_the_same_bytes_on_a_pool_and_on_dask(generated_reference,
                                                                      tmp_path):
    from test_build_engine import _dask_cluster
    scene, want, _ = generated_reference
    assert _sequence_files(scene, tmp_path / "pool", "--workers", "2") == want
    with _dask_cluster(tmp_path, dict(os.environ)) as (address, _):
        got = _sequence_files(scene, tmp_path / "dask", "--engine", "dask", "--address",
                              address)
    assert got == want
