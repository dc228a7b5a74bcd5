"""Scan Animation (issue 36): Blender's animation (keyframes, a Follow Path constraint) scanned
frame by frame as one scene into the sequence format, and imported back as a point cloud that
plays on the timeline. Real Blender (the bpy module), real embree."""

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

import blender_addon  # noqa: E402
from apcg_core.scene import load_sequence  # noqa: E402
from blender_addon import api  # noqa: E402


@pytest.fixture
def scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender_addon.register()
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 5
    bpy.context.scene.render.fps = 10
    yield bpy.context.scene
    blender_addon.unregister()


def _world(obj) -> np.ndarray:
    return np.array([list(r) for r in obj.matrix_world], dtype=np.float64)


def _animated_scene(scene):
    """A lidar, an airliner keyframed across the window and a fighter on a Follow Path."""
    lidar = api.add_lidar()
    jet = api.add_aircraft(lidar, "A320neo", range_m=6000.0, elevation_deg=3.5, yaw_deg=90.0)
    start = np.array(jet.location[:])
    for f, dx in ((1, -20.0), (5, 20.0)):  # lidar-local x: across the line of sight
        jet.location = (start[0] + dx, start[1], start[2])
        jet.keyframe_insert("location", frame=f)
    fighter = api.add_aircraft(lidar, "F-16C Fighting Falcon", range_m=5000.0,
                               elevation_deg=3.45, yaw_deg=-90.0)
    cu = bpy.data.curves.new("path", "CURVE")
    cu.dimensions = "3D"
    spline = cu.splines.new("POLY")
    spline.points.add(1)
    ends = [np.array(fighter.location[:]) + [15.0, 0, 0], np.array(fighter.location[:])
            - [15.0, 0, 0]]
    for p, e in zip(spline.points, ends, strict=True):
        p.co = (*e, 1.0)
    path = bpy.data.objects.new("path", cu)
    scene.collection.objects.link(path)
    fighter.location = (0.0, 0.0, 0.0)  # the path places it; its own location would add
    c = fighter.constraints.new("FOLLOW_PATH")
    c.target, c.use_fixed_location = path, True
    for f, u in ((1, 0.0), (5, 1.0)):
        c.offset_factor = u
        fighter.keyframe_insert('constraints["Follow Path"].offset_factor', frame=f)
    return lidar, jet, fighter, ends


def test_scan_animation_writes_a_sequence_that_follows_the_animation(scene, tmp_path):
    lidar, jet, fighter, ends = _animated_scene(scene)
    expect = {}
    for f in range(1, 6):
        scene.frame_set(f)
        expect[f] = {t.name: _world(t)[:3, 3] for t in (jet, fighter)}
    out = api.scan_animation(lidar, tmp_path / "seq", backend="embree")
    seq = load_sequence(out)
    assert len(seq) == 5 and seq.complete
    assert seq.header["blender"]["frame_start"] == 1 and seq.header["frame_rate_hz"] == 10
    tracks = seq.tracks()
    assert [tracks[i]["type"] for i in (1, 2)] == ["A320neo", "F-16C Fighting Falcon"]
    # the lidar sits at the world origin unturned: lidar-local (x, y, z) is the scene
    # frame's (X, Z, Y)
    for k, f in enumerate(range(1, 6)):
        for tid, obj in ((1, jet), (2, fighter)):
            want = expect[f][obj.name][[0, 2, 1]]
            assert np.abs(tracks[tid]["position"][k] - want).max() < 1e-2, (tid, f)
    assert np.abs(tracks[2]["position"][0] - ends[0][[0, 2, 1]]).max() < 1e-2
    assert np.abs(tracks[2]["position"][-1] - ends[1][[0, 2, 1]]).max() < 1e-2
    assert (tracks[1]["points"] > 0).all() and (tracks[2]["points"] > 0).all()
    for f in seq:  # labels: each target's points sit on it
        for tid in (1, 2):
            pts = f.points_of(tid)
            assert set(f.type[f.instance == tid]) == {tracks[tid]["type"]}
            assert np.linalg.norm(pts.mean(0) - f.position[tid - 1]) < 20.0


def test_an_imported_sequence_plays_on_the_timeline(scene, tmp_path):
    lidar, *_ = _animated_scene(scene)
    out = api.scan_animation(lidar, tmp_path / "seq", backend="embree")
    coll = api.import_sequence(out, lidar=lidar)
    objs = sorted(coll.objects, key=lambda o: o.name)
    assert len(objs) == 5
    seq = load_sequence(out)
    for k, f in enumerate(range(1, 6)):
        scene.frame_set(f)
        shown = [o.name for o in objs if not o.hide_viewport]
        assert shown == [objs[k].name] and not objs[k].hide_render
        inst = np.zeros(len(objs[k].data.vertices), np.int32)
        objs[k].data.attributes["instance"].data.foreach_get("value", inst)
        assert np.array_equal(inst, seq.frame(k).instance)
        got, _ = api.cloud_from_object(objs[k])
        assert np.abs(got.xyz - seq.frame(k).xyz).max() < 1e-3


def test_scan_animation_on_blenders_ray_caster_equals_embree(scene, tmp_path):
    lidar, *_ = _animated_scene(scene)
    a = load_sequence(api.scan_animation(lidar, tmp_path / "a", frame_end=2))  # "blender"
    b = load_sequence(api.scan_animation(lidar, tmp_path / "b", frame_end=2, backend="embree"))
    assert a.header["backend"] == "blender" and len(a) == 2
    for k in range(2):
        fa, fb = a.frame(k), b.frame(k)
        assert len(fa.xyz) > 100
        for name in ("cell_w", "cell_h", "range_m", "instance"):
            assert np.array_equal(getattr(fa, name), getattr(fb, name)), name


def test_the_scan_animation_operator_writes_and_plays_the_sequence(scene, tmp_path):
    lidar, *_ = _animated_scene(scene)
    bpy.context.view_layer.objects.active = lidar
    r = bpy.ops.apcg.scan_animation(directory=str(tmp_path / "seq"), pattern="rows",
                                    line_time_s=1e-3)
    assert r == {"FINISHED"}
    seq = load_sequence(tmp_path / "seq")
    assert len(seq) == 5 and seq.header["scene"]["scan"]["pattern"] == "rows"
    clouds = [o for o in bpy.data.objects if o.name.startswith("APCG sequence seq ")]
    assert len(clouds) == 5
    assert bpy.ops.apcg.import_sequence(directory=str(tmp_path / "seq")) == {"FINISHED"}


# --- bad input: the command line's checks, nothing written -------------------------------------
def _files(directory) -> dict:
    return {str(p.relative_to(directory)): p.read_bytes()
            for p in sorted(directory.rglob("*")) if p.is_file()}


def test_scan_animation_refuses_a_directory_holding_another_sequence(scene, tmp_path, capsys):
    """`apcg scene sequence`'s check (dataset_builder.scene.check_sequence_directory): five
    frames of another scene are neither replaced nor left stale beside three new ones."""
    from test_scene import _write_scene

    from apcg_core.cli import main
    five = _write_scene(tmp_path / "five.toml", {
        "sequence": {"frames": 5, "frame_rate_hz": 10.0},
        "target": [{"type": "737-800", "range_m": 5000.0, "elevation_deg": 3.5}]})
    out = tmp_path / "DIR"
    assert main(["scene", "sequence", str(five), "-o", str(out), "--no-progress"]) == 0
    capsys.readouterr()
    before = _files(out)
    lidar, *_ = _animated_scene(scene)
    with pytest.raises(api.InputError, match="DIR already holds a different sequence"):
        api.scan_animation(lidar, out, frame_end=3, backend="embree")
    assert _files(out) == before
    # its own sequence again is no other sequence: scanned anew, complete
    mine = tmp_path / "mine"
    api.scan_animation(lidar, mine, frame_end=3, backend="embree")
    first = _files(mine)
    api.scan_animation(lidar, mine, frame_end=3, backend="embree")
    assert _files(mine) == first and load_sequence(mine).complete
    with pytest.raises(api.InputError, match="mine already holds a different sequence"):
        api.scan_animation(lidar, mine, frame_end=2, backend="embree")


def test_scan_animation_refuses_a_scan_longer_than_a_frame(scene, tmp_path):
    """The scene file's check (apcg_core.scene.spec.check_scan_fits, made by every Scene):
    64 rows 1 s apart at 24 fps."""
    lidar, *_ = _animated_scene(scene)
    scene.render.fps = 24
    scene.frame_set(2)
    with pytest.raises(api.InputError, match=r"one frame's scan takes 63 s, longer than a frame "
                                             r"at 24 Hz"):
        api.scan_animation(lidar, tmp_path / "seq_f", backend="embree",
                           scan={"pattern": "rows", "line_time_s": 1.0})
    assert not (tmp_path / "seq_f").exists() and scene.frame_current == 2


def test_scan_animation_refuses_the_lidar_inside_a_target_before_writing(scene, tmp_path):
    """A target keyframed through the lidar (5 m from it at frame 3), or onto it: refused
    before frame 0 is written, as `apcg scene sequence` refuses it (one InputError)."""
    lidar = api.add_lidar()
    jet = api.add_aircraft(lidar, "A320neo", range_m=6000.0, elevation_deg=3.5)
    start = np.array(jet.location[:])
    jet.keyframe_insert("location", frame=1)
    jet.location = tuple(-start + [10.0, 0.0, 0.0])
    jet.keyframe_insert("location", frame=5)
    with pytest.raises(api.InputError, match=r"Blender target 1 \(.*\): at t = 0.2 s its range "
                                             r"5 m puts the lidar inside it"):
        api.scan_animation(lidar, tmp_path / "seq", backend="embree")
    assert not (tmp_path / "seq").exists()
    jet.location = (0.0, 0.0, 0.0)
    jet.keyframe_insert("location", frame=5)
    with pytest.raises(api.InputError, match=r"Blender target 1 \(.*\): at frame 5: the "
                                             r"target sits on the lidar"):
        api.scan_animation(lidar, tmp_path / "seq", backend="embree")
    assert not (tmp_path / "seq").exists() and scene.frame_current == 1
