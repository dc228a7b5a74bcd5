"""What a scene's frames and sequences record of themselves (probe p1, stop 55).

* A user catalog type's mesh is stamped into a sequence's record (the catalog's
  ``mesh_record``, as a dataset's header): a sequence directory made from another mesh of the
  same type (`apcg catalog add --force`) is another sequence, refused by name, never resumed
  into a mix of the two meshes' frames. Built-in types stamp nothing (their bytes as before).
* A frame's ``generated`` says whether that target's points in that frame came from its
  model: False for a generated target out of the window (nothing drew it), as for one the
  simulator drew by the fallback rule.
* A ``[target]`` table (single brackets) is named as such.

Real embree, the real catalog (user types under the tests' own data directory, conftest.py),
the shipped model, small windows."""

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from test_scene import _write_scene

from apcg_core.catalog.catalog import default_catalog, mesh_digest
from apcg_core.errors import InputError
from apcg_core.scene import load_scene, load_sequence, read_frame, scene_from_dict
from tests.cli_run import one_error, run

# the user types these tests add stay out of the process's catalog (conftest.py)
pytestmark = pytest.mark.usefixtures("own_catalog")

NAME = "scene stamp plane"
# a small window (64 x 32 cells) at 3 km: every frame a few hundred rays
LIDAR = {"width": 64, "height": 32}


def _plane(span: float) -> trimesh.Trimesh:
    """A fuselage and a wing: two meshes of one name differ in the wing's span only."""
    return trimesh.util.concatenate([trimesh.creation.box(extents=[20.0, 3.0, 3.0]),
                                     trimesh.creation.box(extents=[4.0, span, 0.6])])


def _add(tmp_path: Path, capsys, span: float) -> str:
    """``NAME`` is the plane of ``span`` (added, or replaced with --force); its mesh digest."""
    f = tmp_path / f"plane_{span:g}.stl"
    _plane(span).export(f)
    rc, _, err = run(["catalog", "add", f, "--name", NAME, "--kind", "aircraft", "--force"],
                     capsys)
    assert rc == 0, err
    return mesh_digest(default_catalog().mesh(NAME))


def _user_scene(tmp_path: Path) -> Path:
    return _write_scene(tmp_path / "user.toml", {
        "lidar": LIDAR, "sequence": {"frames": 3, "frame_rate_hz": 10.0},
        "target": [{"type": NAME, "range_m": 3000.0, "elevation_deg": 3.5, "yaw_deg": 40.0},
                   {"type": "A320neo", "range_m": 4000.0, "azimuth_deg": 0.05,
                    "elevation_deg": 3.5}]})


def _seq(scene: Path, out: Path, capsys) -> tuple[int, str, str]:
    return run(["scene", "sequence", scene, "-o", out, "--no-progress"], capsys)


# --- 1. a user type's mesh is part of the sequence ---------------------------------------------
def test_a_sequence_made_from_another_mesh_of_a_user_type_is_refused_not_resumed(tmp_path,
                                                                                 capsys):
    first = _add(tmp_path, capsys, 24.0)
    scene, out = _user_scene(tmp_path), tmp_path / "seq"
    rc, _, err = _seq(scene, out, capsys)
    assert rc == 0, err
    kept = {p.name: p.read_bytes() for p in (out / "frames").glob("*.npz")}
    assert len(kept) == 3

    # a run stopped after two frames, the mesh replaced, the same command again
    (out / "frames" / "000002.npz").unlink()
    (out / "manifest.json").unlink()
    second = _add(tmp_path, capsys, 40.0)
    assert second != first
    rc, _, err = _seq(scene, out, capsys)
    one_error(rc, err, "already holds a different sequence", f"target 1 ({NAME})",
              "its mesh changed", first[:12], second[:12], "catalog add --force")
    assert not (out / "frames" / "000002.npz").exists()  # nothing of the new mesh mixed in
    assert not (out / "manifest.json").exists()
    assert {p.name: p.read_bytes() for p in (out / "frames").glob("*.npz")} == {
        k: v for k, v in kept.items() if k != "000002.npz"}

    # the first mesh back: the same sequence again, resumed to the bytes it had
    assert _add(tmp_path, capsys, 24.0) == first
    rc, out_text, err = _seq(scene, out, capsys)
    assert rc == 0, err
    summary = json.loads(out_text)
    assert summary["built_frames"] == 1 and summary["skipped_frames"] == 2
    assert {p.name: p.read_bytes() for p in (out / "frames").glob("*.npz")} == kept
    assert load_sequence(out).complete

    # where the stamp is: the scene's record and the track (the header), every frame's meta
    head = json.loads((out / "sequence.json").read_text())
    assert head["scene"]["targets"][0]["mesh_sha256"] == first
    assert head["tracks"][0]["mesh_sha256"] == first
    # a built-in type stamps nothing (its sequences keep their bytes and headers)
    assert "mesh_sha256" not in head["scene"]["targets"][1]
    assert "mesh_sha256" not in head["tracks"][1]
    assert all(f.meta["mesh_sha256"] == {"1": first} for f in load_sequence(out))


def test_a_scan_records_the_mesh_its_user_type_was_cast_from(tmp_path, capsys):
    digest = _add(tmp_path, capsys, 30.0)
    scene = _user_scene(tmp_path)
    rc, _, err = run(["scene", "scan", scene, "-o", tmp_path / "one.npz"], capsys)
    assert rc == 0, err
    scan = read_frame(tmp_path / "one.npz")
    assert scan.meta["mesh_sha256"] == {"1": digest}
    assert scan.meta["types"] == [NAME, "A320neo"]
    # a scan is a sequence's frame 0, stamp included
    rc, _, err = _seq(scene, tmp_path / "seq", capsys)
    assert rc == 0, err
    assert (tmp_path / "seq" / "frames" / "000000.npz").read_bytes() == \
        (tmp_path / "one.npz").read_bytes()
    # the scene's digest (what a worker checks its scene by) holds the mesh
    a = scene_from_dict({"lidar": LIDAR, "target": [
        {"type": NAME, "range_m": 3000.0, "elevation_deg": 3.5}]})
    _add(tmp_path, capsys, 31.0)
    b = scene_from_dict({"lidar": LIDAR, "target": [
        {"type": NAME, "range_m": 3000.0, "elevation_deg": 3.5}]})
    assert a.digest() != b.digest()


def test_a_worker_refuses_a_mesh_replaced_while_its_sequence_is_built(tmp_path, capsys):
    from dataset_builder.scene import SequenceTask, run_sequence_task
    _add(tmp_path, capsys, 26.0)
    scene = _user_scene(tmp_path)
    digest = load_scene(scene).digest()
    _add(tmp_path, capsys, 27.0)
    task = SequenceTask(0, str(scene.resolve()), digest, None, (0,), str(tmp_path), "embree",
                        1, True, None, 0)
    with pytest.raises(InputError, match="mesh of a user catalog type it names"):
        run_sequence_task(task)
    assert not (tmp_path / "frames").exists()


def test_built_in_types_stamp_nothing():
    scene = scene_from_dict({"lidar": LIDAR, "target": [
        {"type": "A320neo", "range_m": 3000.0, "elevation_deg": 3.5}]})
    assert "mesh_sha256" not in scene.record["targets"][0]
    assert default_catalog().mesh_record("A320neo") == {}


# --- 2. `generated`: points from the model in this frame ---------------------------------------
GENERATED = {
    "scan": {"pattern": "rows", "line_time_s": 5e-4},
    "sequence": {"frames": 4, "frame_rate_hz": 10.0, "start_s": 0.5},
    "target": [
        # inside the model's space, in the window in every frame: drawn by the model
        {"type": "A320neo", "range_m": 6000.0, "elevation_deg": 3.3, "generator": "default",
         "trajectory": {"kind": "climb", "speed_mps": 80.0, "heading_deg": 160.0,
                        "climb_rate_mps": 4.0}},
        # crossing (yaw outside the model's +-60 deg): simulated by the fallback rule while
        # in the window (frames 0, 1), then out of the window (frames 2, 3): nothing drew it
        {"type": "F-16C Fighting Falcon", "range_m": 5000.0, "azimuth_deg": 1.9,
         "elevation_deg": 3.35, "generator": "default",
         "trajectory": {"kind": "line", "speed_mps": 300.0, "heading_deg": -90.0}}]}


def test_generated_is_false_where_a_generated_target_is_out_of_the_window(tmp_path, capsys):
    scene = _write_scene(tmp_path / "g.toml", GENERATED)
    rc, _, err = _seq(scene, tmp_path / "g", capsys)
    assert rc == 0, err
    seq = load_sequence(tmp_path / "g")
    gen = np.array([f.generated for f in seq])
    inside = np.array([f.in_window for f in seq])
    points = np.array([f.points for f in seq])
    assert inside[:, 0].all() and list(inside[:, 1]) == [True, True, False, False]
    assert points[:2, 1].min() > 0 and (points[2:, 1] == 0).all()
    assert gen[:, 0].all()  # the model drew the airliner in every frame
    assert not gen[:, 1].any()  # the fighter: simulated (frames 0, 1), not drawn (2, 3)
    assert not (gen & ~inside).any()  # nothing drawn outside the window
    assert [set(f.meta["fallback"]) for f in seq] == [{"2"}, {"2"}, set(), set()]
    manifest = json.loads((tmp_path / "g" / "manifest.json").read_text())
    assert manifest["generator"]["2"]["generated_frames"] == 0
    assert manifest["generator"]["2"]["fallback_frames"] == [0, 1]
    assert manifest["generator"]["1"]["generated_frames"] == 4


# --- 3. `[target]` ------------------------------------------------------------------------------
@pytest.mark.parametrize("trajectory", [False, True], ids=["static", "with-trajectory"])
def test_a_single_bracket_target_table_is_named(tmp_path, capsys, trajectory):
    text = '[target]\ntype = "A320neo"\nrange_m = 3000.0\nelevation_deg = 3.5\n'
    if trajectory:
        text += '[target.trajectory]\nkind = "line"\nspeed_mps = 100.0\nheading_deg = 90.0\n'
    (tmp_path / "one.toml").write_text(text)
    rc, _, err = run(["scene", "scan", tmp_path / "one.toml", "-o", tmp_path / "x.npz"], capsys)
    one_error(rc, err, "found [target] (single brackets)", "[[target]]",
              "one [[target]] table per target")
    assert "no [[target]] table" not in err
    assert not (tmp_path / "x.npz").exists()
    # a file with no target at all keeps its own message
    (tmp_path / "none.toml").write_text("[sequence]\nframes = 1\n")
    rc, _, err = run(["scene", "scan", tmp_path / "none.toml", "-o", tmp_path / "x.npz"], capsys)
    one_error(rc, err, "no [[target]] table")


def test_a_sequence_with_photons_is_another_when_a_user_types_reflectivity_changed(
        tmp_path, capsys):
    """`catalog add --force` may keep a user type's mesh and replace its reflectivity, which
    a --sensor sequence's photons depend on: such a sequence is another, not resumed into a
    mix of the two reflectivities' frames."""
    f = tmp_path / "plane.stl"
    _plane(28.0).export(f)

    def add(reflectivity):
        rc, _, err = run(["catalog", "add", f, "--name", NAME, "--kind", "aircraft", "--force",
                          "--reflectivity", str(reflectivity)], capsys)
        assert rc == 0, err
    add(0.3)
    scene, out = _user_scene(tmp_path), tmp_path / "seq"
    cmd = ["scene", "sequence", scene, "-o", out, "--no-progress", "--sensor", "1550nm-night"]
    rc, _, err = run(cmd, capsys)
    assert rc == 0, err
    assert load_scene(scene).record["targets"][0]["reflectivity"] == 0.3
    frames = sorted((out / "frames").glob("*.npz"))
    frames[-1].unlink()  # stopped before its last frame
    add(0.6)
    rc, _, err = run(cmd, capsys)
    one_error(rc, err, "already holds a different sequence")
    assert not (out / "frames" / frames[-1].name).exists()
