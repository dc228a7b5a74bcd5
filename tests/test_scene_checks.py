"""Scene input checks that every path shares (docs/SCENES.md, "Bad input"): a target behind
the lidar is outside the window; the lidar inside a target at any frame is refused before
anything is written; a trajectory CSV file's columns follow the [[target]] keys' rules;
the scan-longer-than-a-frame check belongs to every Scene. Real embree, real catalog types;
each refusal is one line, exit 2, nothing written, no warning before it."""

import warnings

import numpy as np
import pytest
from test_scene import _write_scene

from apcg_core.cli import main
from apcg_core.errors import InputError
from apcg_core.lidar import load_lidar
from apcg_core.scene import make_pattern, scene_from_dict
from apcg_core.scene.poses import POSE_RULES
from apcg_core.scene.spec import Scene, SceneTarget
from apcg_core.scene.trajectory import Sampled


def _refused(argv, capsys, out) -> str:
    """`apcg ARGV` with every warning an error: exit 2, one stderr line, ``out`` absent."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy RuntimeWarning before the refusal fails
        assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert not out.exists(), sorted(p.name for p in out.rglob("*")) if out.is_dir() else out
    return err[0]


# --- a target behind the lidar -----------------------------------------------------------------
@pytest.mark.parametrize("range_m", [6000.0, 100.0])
@pytest.mark.parametrize("azimuth", [180.0, 179.9, -179.9])
def test_a_target_behind_the_lidar_is_outside_the_window(tmp_path, capsys, azimuth, range_m):
    """Its vertices' azimuths wrap at +-180 deg, so their least and greatest once made a box
    over the whole window: a scan of 0 points, "clipped", and a warning."""
    doc = {"pointing": {"azimuth_deg": 0.0, "elevation_deg": 3.5},
           "target": [{"type": "A320neo", "range_m": range_m, "azimuth_deg": azimuth,
                       "elevation_deg": 3.5}]}
    scene = _write_scene(tmp_path / "behind.toml", doc)
    for cmd, out in (("scan", tmp_path / "out.npz"), ("sequence", tmp_path / "seq")):
        argv = ["scene", cmd, str(scene), "-o", str(out)]
        err = _refused(argv + (["--no-progress"] if cmd == "sequence" else []), capsys, out)
        assert "target 1 (A320neo) lies outside the lidar's window" in err, err


def test_a_near_target_that_fills_the_window_is_still_scanned(tmp_path, capsys):
    """The sphere decides only for a target reaching behind the lidar: at 100 m an A320neo
    5 deg off the window's centre still covers it."""
    doc = {"pointing": {"azimuth_deg": 0.0, "elevation_deg": 3.5},
           "target": [{"type": "A320neo", "range_m": 100.0, "azimuth_deg": 5.0,
                       "elevation_deg": 3.5}]}
    scene = _write_scene(tmp_path / "near.toml", doc)
    assert main(["scene", "scan", str(scene), "-o", str(tmp_path / "a.npz")]) == 0
    capsys.readouterr()
    assert len(np.load(tmp_path / "a.npz")["xyz"]) > 1000


# --- the lidar inside a target, at any frame ---------------------------------------------------
def _through_the_lidar_csv(tmp_path) -> dict:
    """A CSV track crossing 5 m in front of the lidar at t = 0.5 s (a frame time), between
    rows."""
    rows = ["t_s,x_m,y_m,z_m,pitch_deg,yaw_deg,roll_deg",
            "0,-1000,0,5,0,0,0", "1,1000,0,5,0,0,0"]
    (tmp_path / "track.csv").write_text("\n".join(rows) + "\n")
    return {"type": "A320neo", "trajectory": {"kind": "csv", "file": "track.csv"}}


@pytest.mark.parametrize("case", ["line", "csv"])
def test_the_lidar_inside_a_target_mid_sequence_is_refused_before_anything_is_written(
        tmp_path, capsys, case):
    if case == "line":  # frame 1 (t = 1 s) puts the A320neo on the lidar
        doc = {"sequence": {"frames": 3, "frame_rate_hz": 1.0},
               "target": [{"type": "A320neo", "range_m": 300.0, "elevation_deg": 3.5,
                           "trajectory": {"kind": "line", "speed_mps": 300.0,
                                          "heading_deg": 180.0, "climb_deg": -3.5}}]}
        says = "at t = 1 s its range"
    else:
        doc = {"sequence": {"frames": 3, "frame_rate_hz": 2.0},
               "target": [_through_the_lidar_csv(tmp_path)]}
        says = "at t = 0.5 s its range 5 m"
    scene = _write_scene(tmp_path / "pass.toml", doc)
    out = tmp_path / "out_pass"
    # with its progress bar on: the refusal comes before the bar
    err = _refused(["scene", "sequence", str(scene), "-o", str(out)], capsys, out)
    assert says in err and "puts the lidar inside it" in err, err


# --- trajectory CSV files: the [[target]] keys' rules ------------------------------------------
HEADER = "t_s,range_m,azimuth_deg,elevation_deg,pitch_deg,yaw_deg,roll_deg"


def _csv_scene(tmp_path, header: str, row: str) -> dict:
    """A scene whose one target follows a CSV file of ``header`` and ``row`` at t = 0, 0.5
    and 1 s (``row`` without its t_s)."""
    lines = [header] + [f"{t},{row}" for t in (0, 0.5, 1)]
    (tmp_path / "track.csv").write_text("\n".join(lines) + "\n")
    return {"sequence": {"frames": 2, "frame_rate_hz": 1.0},
            "target": [{"type": "A320neo", "trajectory": {"kind": "csv", "file": "track.csv"}}]}


@pytest.mark.parametrize("header, row, says", [
    (HEADER + ",rol_deg", "5000,0,3.5,0,0,0,1", "column H: unknown column 'rol_deg'"),
    ("t_s,range_m,azimuth_deg,elevation_deg,x_m,pitch_deg,yaw_deg,roll_deg",
     "5000,0,3.5,9,0,0,0", "the header gives the position twice (range_m, azimuth_deg, "
                           "elevation_deg, x_m)"),
    (HEADER + ",Yaw_deg", "5000,0,3.5,0,0,0,0", "'Yaw_deg' appears twice in the header"),
    (HEADER, "5000,0,90,0,0,0", "column elevation_deg (D): '90' is not accepted: an elevation "
                                "strictly between -90 and 90 deg"),
    (HEADER, "5000,0,95,0,0,0", "column elevation_deg (D): '95' is not accepted"),
    (HEADER, "5000,0,3.5,1e30,0,0", "column pitch_deg (E): '1e30' is not accepted: "
                                    + POSE_RULES["pitch_deg"].accepted),
    (HEADER, "1e30,0,3.5,0,0,0", "column range_m (B): '1e30' is not accepted: "
                                 + POSE_RULES["range_m"].accepted),
    ("t_s,x_m,y_m,z_m,pitch_deg,yaw_deg,roll_deg", "0,0,0,0,0,0",
     "the position (0, 0, 0) lies 0 m from the lidar"),
    ("t_s,x_m,y_m,z_m,pitch_deg,yaw_deg,roll_deg", "0,300,0,0,0,0",
     "lies straight above or below the lidar"),
    ("t_s,x_m,y_m,z_m,pitch_deg,yaw_deg,roll_deg", "0,0,2e6,0,0,0",
     "column z_m (D): '2e6' is not accepted: a finite coordinate in metres from -1e6 to 1e6"),
])
def test_a_trajectory_csv_is_checked_like_the_target_table(tmp_path, capsys, header, row,
                                                           says):
    doc = _csv_scene(tmp_path, header, row)
    with pytest.raises(InputError) as e:
        scene_from_dict(doc, base_dir=tmp_path)
    assert says in str(e.value), str(e.value)
    scene = _write_scene(tmp_path / "csv.toml", doc)
    out = tmp_path / "seq"
    err = _refused(["scene", "sequence", str(scene), "-o", str(out), "--no-progress"], capsys,
                   out)
    assert says in err, err


VALUES = {"range_m": [0.0, -1.0, 1.0, 1e6, 1.000001e6, 1e30],
          "azimuth_deg": [0.0, 360.0, -360.0, 360.5, 1e30],
          "elevation_deg": [3.5, 89.9, -89.9, 90.0, -90.0, 95.0, 1e30],
          "pitch_deg": [0.0, 89.0, 90.0, -91.0, 360.0, -360.0, 361.0, -1e30],
          "yaw_deg": [0.0, 180.0, 360.0, 400.0], "roll_deg": [0.0, 90.5, -360.0, -400.0]}
POSE = {"range_m": 5000.0, "azimuth_deg": 0.0, "elevation_deg": 3.5, "pitch_deg": 0.0,
        "yaw_deg": 0.0, "roll_deg": 0.0}


@pytest.mark.parametrize("key", list(VALUES))
def test_a_csv_column_accepts_what_the_target_key_of_its_name_accepts(tmp_path, key):
    """One rule table (poses.POSE_RULES, from the command line's options.RULES): each value
    is accepted by both or refused by both, with the same "accepted:" text."""
    for v in VALUES[key]:
        pose = {**POSE, key: v}
        table = {"target": [{"type": "A320neo", **pose}]}
        csv = _csv_scene(tmp_path, HEADER, ",".join(repr(pose[k]) for k in POSE))
        for doc in (table, csv):  # the window where the target is, whatever its value
            doc["pointing"] = {"azimuth_deg": 0.0, "elevation_deg": 3.5}
        answers = []
        for doc in (table, csv):
            try:
                scene_from_dict(doc, base_dir=tmp_path)
                answers.append(None)
            except InputError as exc:
                msg = str(exc)
                assert key in msg, msg
                answers.append(msg[msg.index("is not accepted"):])
        assert answers[0] == answers[1], (key, v, answers)


# --- one frame's scan within a frame: every Scene ----------------------------------------------
def test_every_scene_refuses_a_scan_longer_than_a_frame():
    """Made directly (as the add-on's Scan Animation makes it), not from a file."""
    lidar = load_lidar()
    track = Sampled([0.0, 1.0], [[0.0, 300.0, 5000.0]] * 2, np.zeros((2, 3)))
    target = SceneTarget(1, "A320neo", 0, "airliner_narrowbody", track, "target 1")
    rows = make_pattern({"pattern": "rows", "line_time_s": 1.0}, "test")
    with pytest.raises(InputError, match=r"Blender scene \[scan\]: one frame's scan takes 63 s, "
                                         r"longer than a frame at 24 Hz"):
        Scene(lidar, [target], rows, 0.0, 0.06, None, 3, 24.0, 0.0, {}, "Blender scene")
    # and a trajectory that does not hold every time a frame's scan reads
    with pytest.raises(InputError, match="target 1: scene time 1.5 s lies outside its "
                                         "trajectory"):
        Scene(lidar, [target], make_pattern(None, "test"), 0.0, 0.06, None, 4, 2.0, 0.0, {},
              "Blender scene")
