"""The add-on where a scene, a record or an argument is not what add_aircraft left: targets
placed through constraints and parents, swapped meshes, damaged records and cloud objects, bad
meshes and lidar values, photon clouds through files, reproducible LAS, odd API arguments,
Scan Animation's patterns and directories. Real Blender (the bpy module), no mocks."""

import datetime
import hashlib
import json
import re

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from mathutils import Matrix  # noqa: E402

from apcg_core.errors import InputError  # noqa: E402
from apcg_core.io.clouds import read_cloud_attributes  # noqa: E402
from apcg_core.scene.sequence import load_sequence  # noqa: E402
from blender_addon import api  # noqa: E402
from blender_addon.clouds import CLOUD_KEY  # noqa: E402
from blender_addon.objects import LENGTH_KEY, POSE_KEY, pose_moved, stored_pose  # noqa: E402
from tests.addon_helpers import blender_state  # noqa: E402

GOOD = dict(range_m=4500.0, elevation_deg=3.4, pitch_deg=2.0)


@pytest.fixture
def scene(lidar_and_jet):
    return lidar_and_jet


_state = blender_state


def _ranges(obj) -> np.ndarray:
    return api.cloud_from_object(obj)[0].range_m


def _distance(lidar, target) -> float:
    bpy.context.view_layer.update()
    return (target.matrix_world.translation - lidar.matrix_world.translation).length


# --- 1: one placement of a target in its lidar's frame ----------------------------------------
def _constrained(lidar, jet):
    anchor = bpy.data.objects.new("anchor", None)
    bpy.context.scene.collection.objects.link(anchor)
    anchor.location = (0.0, 6000.0, 300.0)
    jet.constraints.new("COPY_LOCATION").target = anchor


def _parent_inverse(lidar, jet):
    jet.matrix_parent_inverse = Matrix.Translation((0.0, 1500.0, 0.0))


def _under_an_empty(lidar, jet):
    rig = bpy.data.objects.new("rig", None)
    bpy.context.scene.collection.objects.link(rig)
    rig.parent = lidar
    rig.location = (0.0, 1200.0, 40.0)
    jet.parent = rig


@pytest.mark.parametrize("place", [_constrained, _parent_inverse, _under_an_empty])
def test_scan_scan_animation_and_the_pose_agree_with_where_blender_draws_the_target(
        scene, tmp_path, place):
    lidar, jet = scene
    place(lidar, jet)
    drawn = _distance(lidar, jet)
    assert abs(drawn - 4500.0) > 500.0  # the setup moved it
    assert api.targets_of(lidar) == [jet]
    assert api.pose_of(jet)["range_m"] == pytest.approx(drawn, abs=0.01)
    assert jet.apcg_target.range_m == pytest.approx(drawn, abs=0.01)  # the panel
    scanned = np.median(_ranges(api.scan(lidar)[0]))
    assert scanned == pytest.approx(drawn, abs=20.0)
    bpy.context.scene.frame_start = bpy.context.scene.frame_end = 1
    frame = next(iter(load_sequence(api.scan_animation(lidar, tmp_path / "seq"))))
    assert np.median(frame.range_m) == pytest.approx(scanned, abs=1.0)


def test_a_plain_target_keeps_its_exact_doubles_and_a_script_move_is_read_at_once(scene):
    lidar, jet = scene
    api.set_pose(jet, 18_123.456789, 0.061, 0.035, 0.2, -0.01, 0.003)
    pose = api.pose_of(jet)
    assert pose == stored_pose(jet) and pose["range_m"] == 18_123.456789  # not float32's
    jet.matrix_basis = Matrix.Translation((0.0, 3000.0, 0.0))  # no update: scan at once
    assert api.pose_of(jet)["range_m"] == pytest.approx(3000.0, abs=1e-3)
    assert np.median(_ranges(api.scan(lidar)[0])) == pytest.approx(3000.0, abs=20.0)


def test_set_pose_places_a_target_through_the_objects_between(scene):
    lidar, jet = scene
    _under_an_empty(lidar, jet)
    api.set_pose(jet, 5000.0, 0.05)
    assert _distance(lidar, jet) == pytest.approx(5000.0, abs=0.01)
    assert not pose_moved(jet) and api.pose_of(jet)["range_m"] == 5000.0


def test_a_target_below_another_lidar_is_that_lidars(scene):
    lidar, jet = scene
    inner = api.add_lidar("inner")
    inner.parent = lidar
    other = api.add_aircraft(inner, "737-800", **GOOD)
    assert api.targets_of(lidar) == [jet] and api.targets_of(inner) == [other]
    assert api.lidar_of(other) == inner


# --- 2: the ray caster's cache knows the object and its mesh ----------------------------------
def test_a_swapped_mesh_is_scanned_as_the_new_mesh_by_the_same_simulator(scene):
    from blender_addon.objects import lidar_params
    from dataset_builder.simulate import Simulator
    lidar, jet = scene
    other = api.add_aircraft(lidar, "737-800", **dict(GOOD, range_m=9000.0))
    with Simulator("blender", lidar_params(lidar)) as sim:
        first = api.scan_target(jet, simulator=sim, occlusion=False)
        jet.data = other.data
        again = api.scan_target(jet, simulator=sim, occlusion=False)
    fresh = api.scan_target(jet, occlusion=False)
    assert len(first.data.vertices) != len(fresh.data.vertices)
    assert np.array_equal(_ranges(again), _ranges(fresh))


# --- 3: a target's records, read by one validating reader -------------------------------------
DAMAGE = {
    "missing key": lambda t: t[POSE_KEY].pop("yaw"),
    "string value": lambda t: t[POSE_KEY].__setitem__("range_m", "abc"),
    "5-element list": lambda t: t.__setitem__(POSE_KEY, [4500.0, 0.05, 0, 0, 0]),
    "int": lambda t: t.__setitem__(POSE_KEY, 5),
    "nan range": lambda t: t[POSE_KEY].__setitem__("range_m", float("nan")),
}


@pytest.mark.parametrize("damage", DAMAGE)
def test_a_damaged_stored_pose_is_recovered_from_the_matrix(scene, damage):
    lidar, jet = scene
    DAMAGE[damage](jet)
    assert api.pose_of(jet)["range_m"] == pytest.approx(4500.0, abs=0.05)
    assert jet.apcg_target.range_m == pytest.approx(4500.0, abs=0.05)  # the panel, no raise
    assert np.median(_ranges(api.scan(lidar)[0])) == pytest.approx(4500.0, abs=20.0)


def test_a_damaged_record_is_named_when_nothing_recovers_it(scene):
    lidar, jet = scene
    DAMAGE["int"](jet)
    with pytest.raises(InputError, match=f"'A320neo': its {POSE_KEY} property is damaged"):
        stored_pose(jet)
    jet[POSE_KEY] = {"range_m": 4500.0}
    jet[LENGTH_KEY] = "x"
    with pytest.raises(InputError, match=f"'A320neo': its {LENGTH_KEY} property is 'x'"):
        api.scan(lidar)


# --- 4: a cloud object's record and attributes, checked in one place --------------------------
def _record(key, value):
    def damage(c):
        info = json.loads(c[CLOUD_KEY])
        info[key] = value
        c[CLOUD_KEY] = json.dumps(info)
    return damage


def _retyped(name, kind, domain):
    def damage(c):
        a = c.data.attributes
        a.remove(a[name])
        a.new(name, kind, domain)
    return damage


CLOUD_DAMAGE = {"r0 null": _record("r0", None), "meta a string": _record("meta", "x"),
                "source unknown": _record("source", 7),
                "photon fields not a list": _record("photon_fields", "label"),
                "delta_range a vector": _retyped("delta_range", "FLOAT_VECTOR", "POINT"),
                "cell_w on edges": _retyped("cell_w", "INT", "EDGE"),
                "cell_h a float": _retyped("cell_h", "FLOAT", "POINT")}


@pytest.mark.parametrize("damage", CLOUD_DAMAGE)
def test_a_damaged_cloud_object_is_named_before_anything_is_written(scene, tmp_path, damage):
    lidar, _ = scene
    cloud = api.scan(lidar)[0]
    CLOUD_DAMAGE[damage](cloud)
    with pytest.raises(InputError, match="import or make the cloud again"):
        api.export_cloud(cloud, tmp_path / "a.ply")
    bpy.context.view_layer.objects.active = cloud
    with pytest.raises(RuntimeError, match="import or make the cloud again"):
        bpy.ops.apcg.export_cloud(filepath=str(tmp_path / "b.ply"))
    assert list(tmp_path.iterdir()) == []


# --- 5: target meshes pass the catalog importer's checks ---------------------------------------
def test_a_target_mesh_with_nan_vertices_or_no_area_is_refused(scene):
    lidar, jet = scene
    for v in list(jet.data.vertices)[:50]:
        v.co = (float("nan"), 0.0, 0.0)
    with pytest.raises(InputError, match="'A320neo'.*non-finite"):
        api.scan(lidar)
    with pytest.raises(InputError, match="non-finite"):
        api.add_to_catalog(jet, name="nan jet")
    line = bpy.data.meshes.new("line")
    line.from_pydata([(0, 0, 0), (2, 0, 0), (4, 0, 0)], [], [(0, 1, 2), (2, 1, 0)])
    jet.data = line
    with pytest.raises(InputError, match="zero area"):
        api.scan(lidar)
    with pytest.raises(InputError, match="every one of its 2 triangles has zero area"):
        api.add_to_catalog(jet, name="line jet")
    from apcg_core.catalog import default_catalog
    assert "line jet" not in default_catalog().names()


def test_make_target_refuses_a_vertex_at_infinity(scene):
    lidar, _ = scene
    bpy.ops.mesh.primitive_cube_add(size=10.0, location=(0.0, -9000.0, 0.0))
    cube = bpy.context.active_object
    cube.data.vertices[0].co = (float("inf"), 0.0, 0.0)
    before = _state()
    with pytest.raises(InputError, match="'Cube'"):
        api.make_target(lidar, cube, forward="X", up="Z")
    assert _state() == before


# --- 6: the lidar object's values, one check for Scan, Write and Read -------------------------
@pytest.mark.parametrize("name,value,says", [
    ("range_resolution_m", 1e9, "range_resolution_m = 1e+09 is more than"),
    ("r_alpha_deg", -1.0, "r_alpha_deg = -1 is less than"),
    ("r_beta_deg", float("nan"), "r_beta_deg = nan"),
    ("width", 10**6, "width = 1000000 is more than")])
def test_lidar_values_beyond_the_panels_limits_are_refused_by_name(scene, tmp_path, name,
                                                                   value, says):
    lidar, _ = scene
    lidar.apcg_lidar[name] = value  # a script or a custom property: Blender does not clamp
    for call in (lambda: api.scan(lidar), lambda: api.write_lidar_file(lidar,
                                                                       tmp_path / "l.toml")):
        with pytest.raises(InputError, match=re.escape(f"lidar 'APCG Lidar': {says}")):
            call()
    assert list(tmp_path.iterdir()) == []


# --- 7 and 8: photon clouds through files; LAS bytes of any day -------------------------------
@pytest.mark.parametrize("ext", ["ply", "npz", "las"])
def test_a_photon_clouds_labels_survive_import_and_export(scene, tmp_path, ext):
    lidar, _ = scene
    ph = api.scan(lidar, sensor="1550nm-day", seed=2)[0]
    want, _ = api.cloud_from_object(ph)
    first = api.export_cloud(ph, tmp_path / f"a.{ext}")
    obj = api.import_cloud(first)
    got, info = api.cloud_from_object(obj)
    assert info["photon_fields"] == ["label", "count"]
    assert np.array_equal(got.label, want.label) and np.array_equal(got.count, want.count)
    back, meta, _ = read_cloud_attributes(api.export_cloud(obj, tmp_path / f"b.{ext}"))
    assert "sensor" in meta
    assert np.array_equal(back.label, want.label) and np.array_equal(back.count, want.count)


@pytest.mark.parametrize("ext", ["las", "laz"])
def test_las_bytes_do_not_depend_on_the_day(scene, tmp_path, monkeypatch, ext):
    import laspy.header as lh
    lidar, _ = scene
    cloud = api.scan(lidar)[0]

    def digest(name):
        return hashlib.sha256((tmp_path / name).read_bytes()).hexdigest()
    monkeypatch.delenv("SOURCE_DATE_EPOCH", raising=False)
    api.export_cloud(cloud, tmp_path / f"today.{ext}")
    real = lh.date

    class Tomorrow(datetime.date):
        @classmethod
        def today(cls):
            return real.today() + datetime.timedelta(days=1)
    monkeypatch.setattr(lh, "date", Tomorrow)
    api.export_cloud(cloud, tmp_path / f"tomorrow.{ext}")
    assert digest(f"today.{ext}") == digest(f"tomorrow.{ext}")
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    api.export_cloud(cloud, tmp_path / f"epoch.{ext}")
    assert laspy_date(tmp_path / f"epoch.{ext}") == datetime.date(2023, 11, 14)


def laspy_date(path):
    import laspy
    with laspy.open(path) as f:
        return f.header.creation_date


# --- 9: an object carrying a pose that is no mesh ---------------------------------------------
def test_an_empty_carrying_a_pose_is_no_target(scene):
    lidar, jet = scene
    marker = bpy.data.objects.new("Marker", None)
    bpy.context.scene.collection.objects.link(marker)
    marker.parent = lidar
    marker[POSE_KEY] = jet[POSE_KEY].to_dict()
    assert api.targets_of(lidar) == [jet]
    assert len(api.scan(lidar)) == 1
    bpy.context.view_layer.objects.active = lidar
    assert bpy.ops.apcg.scan() == {"FINISHED"}
    for call in (lambda: api.scan(lidar, targets=[marker]), lambda: api.generate(marker),
                 lambda: api.pose_of(marker)):
        with pytest.raises(InputError, match="'Marker' carries an APCG pose .* not a mesh"):
            call()


# --- 10: API arguments ------------------------------------------------------------------------
def test_a_numpy_integer_seed_is_the_same_seed(scene):
    lidar, _ = scene
    a = api.cloud_from_object(api.scan(lidar, sensor="1550nm-day", seed=np.int64(3))[0])[0]
    b = api.cloud_from_object(api.scan(lidar, sensor="1550nm-day", seed=3)[0])[0]
    assert np.array_equal(a.range_m, b.range_m) and np.array_equal(a.label, b.label)


@pytest.mark.parametrize("call,says", [
    (lambda lidar, jet: api.scan(lidar, sensor="1550nm-day", seed=None), "seed = None"),
    (lambda lidar, jet: api.scan(lidar, seed=True), "seed = True"),
    (lambda lidar, jet: api.scan(lidar, seed=3.0), "seed = 3.0"),
    (lambda lidar, jet: api.scan_animation(lidar, "sq", frame_start=2**40, frame_end=2**40),
     "frame_start = 1099511627776"),
    (lambda lidar, jet: api.export_cloud(
        next(o for o in lidar.children if api.is_cloud(o)), None), "path = None"),
    (lambda lidar, jet: api.import_cloud(None), "path = None"),
    (lambda lidar, jet: api.import_sequence(None), "directory = None"),
    (lambda lidar, jet: api.generate(jet, count=10**9), "count = 1000000000"),
    (lambda lidar, jet: api.scan(lidar, backend="nope"), "accepted: "),
])
def test_api_arguments_are_refused_by_name(scene, tmp_path, monkeypatch, call, says):
    lidar, jet = scene
    api.scan(lidar)  # a cloud to export
    monkeypatch.chdir(tmp_path)
    before = _state()
    with pytest.raises(InputError) as e:
        call(lidar, jet)
    assert says in str(e.value), str(e.value)
    assert _state() == before and list(tmp_path.iterdir()) == []


def test_the_points_backend_scans_a_target(scene):
    lidar, _ = scene
    ranges = _ranges(api.scan(lidar, backend="points", occlusion=False)[0])
    assert len(ranges) > 20 and np.median(ranges) == pytest.approx(4500.0, abs=20.0)


# --- 11: integer columns never wrap -----------------------------------------------------------
def _npz(path, **cols):
    np.savez(path, xyz=np.array([[0.0, 0.0, 5.0], [0.0, 1.0, 5.0]]), **cols)


@pytest.mark.parametrize("cols,says", [
    (dict(cell_w=np.array([2**40, 1])), "'cell_w' value 1099511627776"),
    (dict(cell_h=np.array([3, 2**32 + 7])), "'cell_h' value 4294967303"),
    (dict(sample=np.array([0, 2**63 - 1], np.uint64) * 2), "'sample' value"),
    (dict(cell_w=np.array([1e12, 0.0])), "'cell_w' value 1000000000000.0"),
])
def test_integer_columns_that_do_not_fit_are_refused(addon_scene, tmp_path, cols, says):
    path = tmp_path / "big.npz"
    _npz(path, **cols)
    with pytest.raises(InputError, match="big.npz") as e:
        api.import_cloud(path)
    assert says in str(e.value) and "accepted: whole numbers from" in str(e.value)


def test_a_ply_double_cell_that_does_not_fit_is_refused(addon_scene, tmp_path):
    path = tmp_path / "big.ply"
    rec = np.array([(0.0, 0.0, 5.0, 1e12)], dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"),
                                                  ("cell_w", "<f8")])
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n"
                     b"property double x\nproperty double y\nproperty double z\n"
                     b"property double cell_w\nend_header\n" + rec.tobytes())
    with pytest.raises(InputError, match="big.ply: its 'cell_w' value 1000000000000.0"):
        api.import_cloud(path)


# --- 12: Scan Animation's patterns at their defaults ------------------------------------------
@pytest.mark.parametrize("pattern", ["rows", "columns"])
@pytest.mark.parametrize("frames", [(1, 3), (1, 1)])
def test_scan_animation_patterns_work_at_their_defaults(scene, tmp_path, pattern, frames):
    lidar, _ = scene
    sc = bpy.context.scene
    sc.frame_start, sc.frame_end = frames
    bpy.context.view_layer.objects.active = lidar
    out = tmp_path / "seq"
    assert bpy.ops.apcg.scan_animation(directory=str(out), pattern=pattern,
                                       backend="blender") == {"FINISHED"}
    assert (out / "manifest.json").exists()


def test_a_one_frame_scan_longer_than_a_frame_says_so(scene, tmp_path):
    lidar, _ = scene
    bpy.context.scene.frame_start = bpy.context.scene.frame_end = 1
    with pytest.raises(InputError, match="longer than a frame"):
        api.scan_animation(lidar, tmp_path / "seq", scan={"pattern": "rows",
                                                          "line_time_s": 1e-3})
    assert list(tmp_path.iterdir()) == []


# --- 13: a range inside the target; generate's condition named --------------------------------
def test_a_range_inside_the_target_is_refused_where_it_is_given(scene):
    lidar, jet = scene
    before = _state()
    with pytest.raises(InputError, match="target 'too close': range_m = 20 m puts the lidar "
                                         "inside"):
        api.add_aircraft(lidar, "A320neo", **dict(GOOD, range_m=20.0), name="too close")
    assert _state() == before
    with pytest.raises(InputError, match="target 'A320neo': range_m = 15 m"):
        api.set_pose(jet, 15.0, 0.05)
    jet.location = (0.0, 5.0, 0.0)
    with pytest.raises(InputError, match="target 'A320neo': range_m = 5 m"):
        api.scan(lidar)


def test_the_api_docstring_example_generates_and_a_refused_condition_names_target_and_model(
        scene):
    lidar, _ = scene
    jet = api.add_aircraft(lidar, "A320neo", range_m=4500, elevation_deg=3.4, pitch_deg=2.0,
                           yaw_deg=13.2)
    assert "pitch_deg=2.0" in api.__doc__
    assert len(api.generate(jet, seed=0).data.vertices) > 0
    flat = api.add_aircraft(lidar, "A320neo", range_m=4500, elevation_deg=3.4, name="Flat")
    with pytest.raises(InputError, match=r"target 'Flat' \(A320neo\) for the model .*default"
                                         r".*pitch = 0 deg"):
        api.generate(flat, seed=0)


# --- 14: Scan Animation writes into a new or empty directory, or its own sequence's -----------
@pytest.mark.parametrize("mine", [{"notes.txt": "mine"}, {"frames/000000.npz": "not ours"},
                                  {"frames/readme": "x"}])
def test_scan_animation_leaves_a_directory_of_other_files_alone(scene, tmp_path, mine):
    lidar, _ = scene
    out = tmp_path / "project"
    for name, text in mine.items():
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text(text)
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    bpy.context.scene.frame_end = 1
    with pytest.raises(InputError, match=r"project.*no sequence\.json"):
        api.scan_animation(lidar, out)
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
    assert all((out / n).read_text() == t for n, t in mine.items())
    empty = tmp_path / "empty"
    empty.mkdir()
    api.scan_animation(lidar, empty)
    assert (empty / "manifest.json").exists()


# --- 15: another tool's cloud: its points sized by their spacing, float32's limit named ------
def _radius(obj) -> float:
    from blender_addon.clouds import _radius_identifier
    mod = obj.modifiers["APCG points"]
    return float(mod[_radius_identifier(mod.node_group)])


def test_a_georeferenced_cloud_gets_points_its_size_and_a_huge_one_is_named(addon_scene,
                                                                             tmp_path):
    grid = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0)), -1).reshape(-1, 2)
    xyz = np.column_stack([grid + [4.5e6, 5.4e6], np.full(len(grid), 300.0)])  # 1 m apart
    np.savez(tmp_path / "geo.npz", xyz=xyz)
    assert 0.1 < _radius(api.import_cloud(tmp_path / "geo.npz")) < 1.0
    np.savez(tmp_path / "huge.npz", xyz=np.array([[1e39, 0.0, 0.0], [0.0, 1.0, 5.0]]))
    before = _state()
    with pytest.raises(InputError, match="huge.npz.*float32"):
        api.import_cloud(tmp_path / "huge.npz")
    assert _state() == before
