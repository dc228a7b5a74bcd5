"""The add-on's Python API refuses what it cannot use the way the command line does (one
InputError naming the value and what is accepted), before it changes the scene; in real
Blender (the bpy module)."""

import inspect

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from apcg_core.catalog import default_catalog  # noqa: E402
from apcg_core.errors import InputError  # noqa: E402
from blender_addon import api  # noqa: E402
from tests.addon_helpers import blender_state  # noqa: E402

GOOD = dict(range_m=4500.0, elevation_deg=3.4, pitch_deg=2.3)


@pytest.fixture
def scene(lidar_and_jet):
    return lidar_and_jet


_state = blender_state


BAD_POSES = [dict(range_m=float("nan")), dict(range_m=0.0), dict(range_m=-5.0),
             dict(range_m=1e30), dict(range_m="abc"), dict(range_m=None),
             dict(elevation_deg=95.0), dict(elevation_deg=90.0), dict(pitch_deg=1e30),
             dict(pitch_deg=120.0), dict(yaw_deg=float("inf")), dict(roll_deg=True)]


@pytest.mark.parametrize("bad", BAD_POSES, ids=lambda d: "-".join(f"{k}={v}" for k, v in
                                                                 d.items()))
def test_a_refused_pose_leaves_the_scene_as_it_was(scene, bad):
    """A pose refused by add_aircraft or make_target makes nothing: a half-made object at the
    lidar would hide every later scan (it did: 235 points -> 0)."""
    lidar, jet = scene
    n = len(api.cloud_from_object(api.scan(lidar, occlusion=True)[0])[0])
    bpy.ops.mesh.primitive_cube_add(size=10.0, location=(0.0, -200.0, 0.0))  # behind
    cube = bpy.context.active_object
    before = _state()
    makers = [lambda: api.add_aircraft(lidar, "A320neo", **{**GOOD, **bad})]
    if bad != {"range_m": None}:  # make_target's range None: its default range, by design
        makers.append(lambda: api.make_target(lidar, cube, **{**GOOD, **bad}))
    for make in makers:
        with pytest.raises(InputError) as e:
            make()
        name = next(iter(bad))
        assert name.split("_")[0] in str(e.value), str(e.value)
        assert _state() == before
    again = api.cloud_from_object(api.scan(lidar, targets=[jet])[0])[0]
    assert len(again) == n > 0


# the API's functions whose first argument is a scene object, and the rest of a valid call
OBJECT_CALLS = {
    "scan_target": {}, "scan": {}, "generate": {}, "pose_of": {}, "set_pose": {
        "range_m": 4500.0, "elevation": 0.06}, "cloud_from_object": {}, "add_to_catalog": {},
    "add_aircraft": {"type_name": "A320neo", **GOOD}, "make_target": {"obj": "cube"},
    "read_lidar_file": {"ref": "1550nm-day"}, "write_lidar_file": {"path": "x.toml"},
    "scan_animation": {"directory": "seq"}, "export_cloud": {"path": "x.ply"},
    "set_point_radius": {"radius": 0.5}, "targets_of": {}, "world_mesh": {},
}


def test_every_function_taking_an_object_refuses_what_is_not_one(scene, tmp_path,
                                                                   monkeypatch):
    """None, a name, a number and a plain mesh, given where the API takes a lidar, target or
    cloud: an InputError naming it, never an AttributeError from inside."""
    lidar, jet = scene
    monkeypatch.chdir(tmp_path)
    bpy.ops.mesh.primitive_cube_add(size=10.0, location=(0.0, -200.0, 0.0))  # behind
    cube = bpy.context.active_object
    takes_object = sorted(n for n in api.__all__ if callable(getattr(api, n)) and next(
        iter(inspect.signature(getattr(api, n)).parameters), "") in ("lidar", "target", "obj"))
    predicates = {"is_lidar", "is_target", "is_cloud", "axes_label"}  # a plain answer
    assert set(takes_object) - predicates <= set(OBJECT_CALLS), takes_object
    for name in sorted(predicates):
        for bad in (None, "A320neo", 5, cube):
            assert not getattr(api, name)(bad)
    for name in sorted(set(takes_object) - predicates):
        fn, rest = getattr(api, name), dict(OBJECT_CALLS[name])
        rest = {k: (cube if v == "cube" else v) for k, v in rest.items()}
        for bad in (None, "A320neo", 5, cube):
            if name == "make_target" and bad is None:
                continue  # None: the scene's first lidar, by design
            if name == "world_mesh" and bad is cube:
                continue  # any mesh object has one
            with pytest.raises(InputError) as e:
                fn(bad, **rest)
            assert repr(getattr(bad, "name", bad)) in str(e.value), (name, bad, str(e.value))


@pytest.mark.parametrize("call, says", [
    (lambda lidar, jet: api.scan(lidar, seed=float("nan")), "seed = nan"),
    (lambda lidar, jet: api.scan(lidar, seed=-1), "seed = -1"),
    (lambda lidar, jet: api.scan(lidar, supersample=0), "supersample = 0"),
    (lambda lidar, jet: api.scan(lidar, targets=jet), "must be a list"),
    (lambda lidar, jet: api.scan(lidar, targets=["A320neo"]), "'A320neo' is not an APCG"),
    (lambda lidar, jet: api.generate(jet, count=0), "count = 0"),
    (lambda lidar, jet: api.generate(jet, count=2.5), "count = 2.5"),
    (lambda lidar, jet: api.generate(jet, seed=-1), "seed = -1"),
    (lambda lidar, jet: api.generate(jet, model=5), "got 5"),
    (lambda lidar, jet: api.generate(jet, model=__file__), "is a file, not a directory"),
    (lambda lidar, jet: api.scan_animation(lidar, "seq", frame_start=float("nan")),
     "frame_start = nan"),
    (lambda lidar, jet: api.scan_animation(lidar, "seq", seed=2**40), "seed = "),
])
def test_numbers_and_options_follow_the_command_lines_rules(scene, tmp_path, monkeypatch,
                                                            call, says):
    lidar, jet = scene
    monkeypatch.chdir(tmp_path)
    before = _state()
    with pytest.raises(InputError, match=None) as e:
        call(lidar, jet)
    assert says in str(e.value), str(e.value)
    assert _state() == before
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("scale", [(2.0, 2.0, 2.0), (-1.0, 1.0, 1.0), (0.0, 0.0, 0.0),
                                   (1.0, 1.0, 0.5)])
def test_a_scaled_target_is_refused_by_its_scale(scene, scale):
    """The simulator and the models cast a target's mesh as it is: a scaled object would not
    be what Blender shows, so scan and generate name its scale instead."""
    lidar, jet = scene
    jet.scale = scale
    for call in (lambda: api.scan(lidar, targets=[jet]), lambda: api.generate(jet)):
        with pytest.raises(InputError, match="has scale"):
            call()
    jet.scale = (1.0, 1.0, 1.0)
    assert len(api.cloud_from_object(api.scan(lidar, targets=[jet])[0])[0]) > 0


def test_files_the_api_cannot_use_are_named(scene, tmp_path):
    lidar, jet = scene
    cloud = api.scan(lidar)[0]
    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(InputError, match="is a directory"):
        api.export_cloud(cloud, tmp_path / "dir.ply")
    with pytest.raises(InputError, match="is a directory"):
        api.write_lidar_file(lidar, tmp_path / "dir.ply")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.ply"]  # no .part left
    np.savez(tmp_path / "shape.npz", xyz=np.zeros((3, 2)))
    np.savez(tmp_path / "nan.npz", xyz=np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0]]))
    with pytest.raises(InputError, match=r"shape \(3, 2\)"):
        api.import_cloud(tmp_path / "shape.npz")
    with pytest.raises(InputError, match="not a finite number"):
        api.import_cloud(tmp_path / "nan.npz")
    cloud["apcg_cloud"] = "{broken"
    with pytest.raises(InputError, match="apcg_cloud"):
        api.cloud_from_object(cloud)


def test_a_cancelled_operator_leaves_the_scene_as_it_found_it(scene, tmp_path):
    """Operators that fail half-way remove what they made: Make Target's new lidar for a mesh
    it then refuses, Import Cloud's object for metadata it then refuses, Import Sequence's
    collection and frames before a damaged frame."""
    lidar, jet = scene
    bpy.data.objects.remove(lidar)  # no lidar: Make Target would add one
    me = bpy.data.meshes.new("pts")
    me.vertices.add(3)
    pts = bpy.data.objects.new("Pts", me)
    bpy.context.scene.collection.objects.link(pts)
    bpy.context.view_layer.objects.active = pts
    before = _state()
    with pytest.raises(RuntimeError, match="no faces"):
        bpy.ops.apcg.make_target()
    assert _state() == before
    np.savez(tmp_path / "r.npz", xyz=np.random.default_rng(0).random((10, 3)) + [0, 3000, 0],
             range_m=np.full(10, np.nan))
    with pytest.raises(RuntimeError, match="'range_m' values are not finite"):
        bpy.ops.apcg.import_cloud(filepath=str(tmp_path / "r.npz"))
    import json
    np.savez(tmp_path / "m.npz", xyz=np.ones((4, 3)) * 3000.0,
             meta=np.array(json.dumps({"condition": {"range_m": float("nan")}})))
    with pytest.raises(RuntimeError, match="condition.range_m"):
        bpy.ops.apcg.import_cloud(filepath=str(tmp_path / "m.npz"))
    assert _state() == before


def test_a_damaged_sequence_imports_nothing(scene, tmp_path):
    lidar, jet = scene
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 3
    seq = tmp_path / "seq"
    api.scan_animation(lidar, seq)
    frame = seq / "frames" / "000001.npz"
    frame.write_bytes(frame.read_bytes()[:200])
    before = _state() + (len(bpy.data.collections),)
    with pytest.raises(InputError, match="000001.npz"):
        api.import_sequence(seq)
    assert _state() + (len(bpy.data.collections),) == before
    (seq / "sequence.json").write_text("{broken")
    with pytest.raises(InputError, match="sequence.json"):
        api.import_sequence(seq)


def test_scan_animation_refuses_a_scaled_target_and_an_empty_directory(scene, tmp_path,
                                                                      monkeypatch):
    lidar, jet = scene
    monkeypatch.chdir(tmp_path)
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 2
    with pytest.raises(InputError, match="give the directory"):
        api.scan_animation(lidar, "")
    jet.scale = (2.0, 2.0, 2.0)
    with pytest.raises(InputError, match="has scale"):
        api.scan_animation(lidar, tmp_path / "seq")
    assert list(tmp_path.iterdir()) == []


def test_read_lidar_reads_what_write_lidar_wrote_and_refuses_before_changing(scene, tmp_path):
    """Write Lidar's file, with its [sensor] table, reads back (it was refused as a sensor
    file); a value the lidar object cannot hold is refused with nothing changed (it was
    clamped, or half the file applied)."""
    lidar, jet = scene
    lidar.apcg_lidar.sensor = "1550nm-day"
    bpy.context.view_layer.objects.active = lidar
    out = tmp_path / "rt.toml"
    assert bpy.ops.apcg.write_lidar(filepath=str(out)) == {"FINISHED"}
    lidar.apcg_lidar.sensor = "ideal"
    assert bpy.ops.apcg.read_lidar(filepath=str(out)) == {"FINISHED"}
    assert lidar.apcg_lidar.sensor == str(out) and api.sensor_of(lidar).name == "1550nm-day"
    assert len(api.cloud_from_object(api.scan(lidar)[0])[0]) > 0
    big = tmp_path / "big.toml"
    big.write_text(out.read_text().replace("width = 256", "width = 20000"))
    assert "width = 20000" in big.read_text()
    with pytest.raises(RuntimeError, match="width = 20000 is more than a lidar object holds"):
        bpy.ops.apcg.read_lidar(filepath=str(big))
    assert lidar.apcg_lidar.width == 256 and lidar.apcg_lidar.sensor == str(out)


def test_operators_name_the_target_and_the_file(scene, tmp_path):
    lidar, jet = scene
    empty = bpy.data.objects.new("Not a lidar", None)
    bpy.context.scene.collection.objects.link(empty)
    jet.parent = empty
    bpy.context.view_layer.objects.active = jet
    with pytest.raises(RuntimeError, match="'A320neo' is not parented to an APCG lidar"):
        bpy.ops.apcg.scan()
    jet.parent = lidar
    cloud = api.scan(lidar)[0]
    bpy.context.view_layer.objects.active = cloud
    (tmp_path / "file").write_text("x")
    with pytest.raises(RuntimeError, match="is a file, so"):
        bpy.ops.apcg.export_cloud(filepath=str(tmp_path / "file" / "a.ply"))
    with pytest.raises(RuntimeError) as e:
        bpy.ops.apcg.export_cloud(filepath="/proc/apcg-test.ply")
    assert "cannot write or read /proc/apcg-test.ply:" in str(e.value) and ".part" not in str(
        e.value)
    bpy.context.view_layer.objects.active = jet
    # its default category is accepted (the add-on's "other" was not a category)
    assert bpy.ops.apcg.add_to_catalog(type_name="My A320neo") == {"FINISHED"}
    assert default_catalog().get("My A320neo").category == "user"


def test_the_panels_pose_fields_never_raise(scene):
    """The panel reads a target's pose at every redraw: a scaled target shows its last pose
    (Scan names the scale), a field set resets the scale, and a value no pose takes leaves
    the target as it was."""
    lidar, jet = scene
    jet.scale = (2.0, 2.0, 2.0)
    assert jet.apcg_target.range_m == pytest.approx(GOOD["range_m"])
    jet.apcg_target.range_m = 5000.0
    assert tuple(jet.scale) == pytest.approx((1.0, 1.0, 1.0))
    assert api.pose_of(jet)["range_m"] == pytest.approx(5000.0)
    jet.apcg_target.range_m = 0.0
    assert api.pose_of(jet)["range_m"] == pytest.approx(5000.0)
