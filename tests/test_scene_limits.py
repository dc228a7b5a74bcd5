"""Scenes at their edges: turns at any rate, frame times that stay apart, and the warnings a
scan owes its user (targets that overlap, clouds cut at the window or emptied by the
sensor), each naming the target. Real embree, real scenes, small sizes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from apcg_core.errors import InputError
from apcg_core.scene import scene_from_dict
from apcg_core.scene.trajectory import Start, Turn
from tests.cli_run import run
from tests.test_scene import _write_scene

START = Start(5000.0, 0.0, 3.0 * math.pi / 180, (0.0, 0.0, 0.0))
T = np.linspace(0.0, 20.0, 201)


def _line(heading_deg: float) -> np.ndarray:
    h = math.radians(heading_deg)
    return Turn(START, 200.0, heading_deg, 0.0).p0 + T[:, None] * 200.0 * np.array(
        [math.sin(h), 0.0, math.cos(h)])


@pytest.mark.parametrize("rate", [1e-320, 1e-13, 1e-11, 1e-9])
def test_a_turn_at_a_tiny_rate_is_the_straight_line(rate):
    p, _ = Turn(START, 200.0, 45.0, rate).poses(T)
    assert np.isfinite(p).all()
    # the arc's sagitta over 4 km at this rate, and a few ulps of 5 km
    allowed = 200.0 * 20.0 ** 2 * math.radians(rate) + 1e-8
    assert np.abs(p - _line(45.0)).max() <= allowed, np.abs(p - _line(45.0)).max()


@pytest.mark.parametrize("rate", [-12.0, 0.5, 3.0, 720.0])
def test_a_turn_flies_its_circle_at_its_speed(rate):
    """Every position on the circle of radius v / omega about its centre, the chord from the
    start 2 (v / omega) sin(omega t / 2) long, the heading omega t turned."""
    tr = Turn(START, 200.0, 30.0, rate)
    p, rot = tr.poses(T)
    w = math.radians(rate)
    k = 200.0 / w
    h0 = math.radians(30.0)
    centre = tr.p0 + k * np.array([math.cos(h0), 0.0, -math.sin(h0)])
    radius = np.sqrt(((p - centre) ** 2).sum(-1))
    assert np.allclose(radius, abs(k), rtol=1e-12, atol=1e-9)
    chord = np.sqrt(((p - tr.p0) ** 2).sum(-1))
    assert np.allclose(chord, np.abs(2 * k * np.sin(w * T / 2)), rtol=1e-12, atol=1e-9)
    heading = np.arctan2(rot[:, 0, 0], rot[:, 2, 0])  # the nose (body x) in the scene frame
    assert np.allclose(np.angle(np.exp(1j * (heading - h0 - w * T))), 0.0, atol=1e-9)


def _doc(sequence: dict, targets=None) -> dict:
    return {"sequence": sequence,
            "target": targets or [{"type": "A320neo", "range_m": 4500.0,
                                   "elevation_deg": 3.5}]}


@pytest.mark.parametrize("sequence, says", [
    ({"frames": 4, "start_s": 1e17}, "start_s = 1e+17 is not accepted: a time in seconds "
                                     "from -1e+10 to 1e+10"),
    ({"frames": 4, "start_s": -1e300}, "start_s = -1e+300 is not accepted"),
    ({"frames": 3, "frame_rate_hz": 1e-300}, "its last frame is at 2e+300 s"),
    ({"frames": 3, "frame_rate_hz": 1e6, "start_s": 9.9e9},
     "both fall at 9900000000.00000"),
])
def test_frame_times_must_each_be_their_own(sequence, says):
    with pytest.raises(InputError) as err:
        scene_from_dict(_doc(sequence), "s.toml")
    assert says in str(err.value) and str(err.value).startswith("s.toml [sequence]: "), \
        str(err.value)


def test_unix_times_are_frame_times():
    scene = scene_from_dict(_doc({"frames": 5, "frame_rate_hz": 10.0, "start_s": 1.8e9}))
    assert (np.diff(scene.frame_times()) > 0).all()


def _warnings(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if "warning:" in ln]


def test_targets_in_one_place_are_named_and_formation_is_not(tmp_path, capsys):
    same = {"type": "A320neo", "range_m": 4500.0, "elevation_deg": 3.5}
    scene = _write_scene(tmp_path / "same.toml",
                         _doc({"frames": 1}, [same, {**same, "type": "737-800"}]))
    rc, _, err = run(["scene", "scan", scene, "-o", tmp_path / "a.npz"], capsys)
    assert rc == 0, err
    said = [w for w in _warnings(err) if "overlap" in w]
    assert len(said) == 1 and "target 1 (A320neo) and" in said[0] \
        and "target 2 (737-800) overlap" in said[0], err
    # two airliners a wingspan apart (0.5 deg of azimuth at 4.5 km: 39 m): a formation
    apart = {**same, "azimuth_deg": 0.5}
    scene = _write_scene(tmp_path / "formation.toml",
                         _doc({"frames": 1}, [same, {**apart, "type": "737-800"}]))
    rc, _, err = run(["scene", "scan", scene, "-o", tmp_path / "b.npz"], capsys)
    assert rc == 0 and not [w for w in _warnings(err) if "overlap" in w], err
    # a sequence says in how many frames, and from when: the two pass through each other
    # (39 m apart at t = 0, closing at 200 m/s: 0.8 m apart at 0.2 s, 39 m again at 0.4)
    moving = {**apart, "type": "737-800",
              "trajectory": {"kind": "line", "speed_mps": 200.0, "heading_deg": -90.0}}
    scene = _write_scene(tmp_path / "pass.toml",
                         _doc({"frames": 5, "frame_rate_hz": 5.0}, [same, moving]))
    rc, _, err = run(["scene", "sequence", scene, "-o", tmp_path / "seq", "--no-progress"],
                     capsys)
    said = [w for w in _warnings(err) if "overlap" in w]
    assert rc == 0 and len(said) == 1 and "(1 of 5 frame(s))" in said[0] \
        and "t = 0.2 s" in said[0], err


def test_a_cut_cloud_is_named_by_its_target_in_a_scan_and_a_sequence(tmp_path, capsys):
    near = {"type": "A320neo", "range_m": 600.0, "elevation_deg": 3.5}
    far = {"type": "Mavic 3", "range_m": 300.0, "elevation_deg": 3.6}
    scene = _write_scene(tmp_path / "cut.toml", _doc({"frames": 3}, [far, near]))
    for cmd, out in (("scan", "a.npz"), ("sequence", "seq")):
        rc, _, err = run(["scene", cmd, scene, "-o", tmp_path / out, "--no-progress"][
            :None if cmd == "sequence" else -1], capsys)
        said = [w for w in _warnings(err) if "window's edge" in w]
        frames = 1 if cmd == "scan" else 3
        assert rc == 0 and len(said) == 1, err
        assert f"target 2 (A320neo) reaches beyond the lidar's window in {frames} of " \
               f"{frames} frame(s)" in said[0], said


def test_a_target_outside_the_photon_gate_is_named_with_the_gate(tmp_path, capsys):
    far = {"type": "A320neo", "range_m": 8000.0, "elevation_deg": 3.5}
    near = {"type": "737-800", "range_m": 6000.0, "elevation_deg": 3.5, "azimuth_deg": 0.6}
    scene = _write_scene(tmp_path / "gate.toml", _doc({"frames": 1}, [far, near]))
    rc, out, err = run(["scene", "scan", scene, "-o", tmp_path / "a.npz", "--sensor",
                        "1064nm-night", "--seed", "3"], capsys)
    assert rc == 0, err
    said = [w for w in _warnings(err) if "sensor recorded none" in w]
    assert len(said) == 1 and "target 2 (737-800)" in said[0] \
        and "its range 6000 m lies outside the photon gate (8000 +-" in said[0], err
    # the same scene without a sensor: both targets have points, nothing to say
    rc, out, err = run(["scene", "scan", scene, "-o", tmp_path / "b.npz"], capsys)
    assert rc == 0 and not [w for w in _warnings(err) if "sensor" in w], err
