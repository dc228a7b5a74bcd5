"""Blender scene objects as targets, in real Blender (the bpy module, and a real Blender window
for the screenshot): Make Target (modifiers applied, the object's real size, its axes guessed
or stated), Scan against the embree simulator, Generate where the model knows the type, and
Add to Catalog for the command line."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from apcg_core.catalog import default_catalog  # noqa: E402
from apcg_core.catalog.importer import axis_matrix  # noqa: E402
from apcg_core.catalog.mesh import Mesh  # noqa: E402
from apcg_core.errors import InputError  # noqa: E402
from blender_addon import api  # noqa: E402
from blender_addon.objects import AXES_KEY, LENGTH_KEY, SOURCE_KEY, TYPE_KEY  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "data"))
import box_aircraft as box  # noqa: E402
from blender_window import run_in_window, virtual_display  # noqa: E402

APCG = [sys.executable, "-m", "apcg_core.cli"]
POSE = dict(range_m=1500.0, elevation_deg=3.5, pitch_deg=2.0, yaw_deg=35.0, roll_deg=-3.0)
GEN_POSE = dict(POSE, range_m=4500.0)  # inside the model's condition space


@pytest.fixture
def scene(addon_scene):
    """An empty scene with the add-on, and a user catalog of its own (conftest.py)."""
    return addon_scene


def _expected_body() -> Mesh:
    """The box aircraft in the body frame, built without Blender: its world-oriented boxes
    (nose -Y, up Z) turned by the importer's axis matrix, centred at the volume centroid."""
    v, f = box.box_mesh()
    m = Mesh(v, f).transformed(axis_matrix("-Y", "Z"))
    return m.transformed(offset=-m.centroid)


def _verts(obj) -> np.ndarray:
    co = np.empty(3 * len(obj.data.vertices), np.float32)
    obj.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3).astype(np.float64)


def _select(obj) -> None:
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj


def test_box_aircraft_is_closed_and_outward():
    v, f = box.box_mesh()
    rep = Mesh(v, f).report()
    assert rep.watertight and rep.volume > 0 and rep.n_bodies == len(box.BOXES)


def test_make_target_applies_modifiers_scale_and_rotation(scene):
    models = bpy.data.collections.new("Models")
    scene.collection.children.link(models)
    src = box.add_box_aircraft(collection=models)
    matrix_before = [list(r) for r in src.matrix_world]
    n_before = len(src.data.vertices)
    lidar = api.add_lidar()
    target = api.make_target(lidar, src, **POSE)  # axes guessed
    # a new object in the source's collection; the source is left exactly as it was
    assert target is not src and target.name == "Box jet (target)"
    assert target.users_collection[0] == models and target.parent == lidar
    assert not api.is_target(src) and TYPE_KEY not in src
    assert [list(r) for r in src.matrix_world] == matrix_before
    assert len(src.data.vertices) == n_before and src.modifiers["Mirror"].show_viewport
    assert target[SOURCE_KEY] == src
    # the guess: nose along -Y, up Z; the body mesh at the world size, Mirror applied
    axes = target[AXES_KEY]
    assert (axes["forward"], axes["up"], axes["how"]) == ("-Y", "Z", "guessed")
    assert api.axes_label(target) == "forward -Y, up Z (guessed)"
    got = _verts(target)
    ext = got.max(axis=0) - got.min(axis=0)
    assert ext == pytest.approx([box.LENGTH_M, box.SPAN_M, box.HEIGHT_M], abs=1e-4)
    assert len(got) == 2 * n_before  # both halves: the modifier was applied
    exp = _expected_body()
    assert np.abs(got.min(axis=0) - exp.bounds[0]).max() < 1e-4  # centred as the importer
    assert np.abs(got.max(axis=0) - exp.bounds[1]).max() < 1e-4
    assert axes["centre"] == "volume centroid"
    # the nose is +x, the fin on top (+z) at the tail (-x), the wings span y
    fin = got[got[:, 2] > exp.bounds[1][2] - 0.5]
    assert fin[:, 0].max() < 0 and np.abs(fin[:, 1]).max() < 0.21
    assert target[TYPE_KEY] == "Box jet" and target[LENGTH_KEY] == pytest.approx(30.0)
    assert api.pose_of(target)["range_m"] == POSE["range_m"]
    assert target.apcg_target.yaw_deg == pytest.approx(POSE["yaw_deg"])


def test_stated_axes_and_the_operator(scene):
    src = box.add_box_aircraft()
    lidar = api.add_lidar()
    wrong = api.make_target(lidar, src, 4500.0, forward="X", up="Z")  # stated, even if wrong
    assert wrong[AXES_KEY]["how"] == "stated"
    ext = np.ptp(_verts(wrong), axis=0)
    assert ext == pytest.approx([box.SPAN_M, box.LENGTH_M, box.HEIGHT_M], abs=1e-4)
    # the operator: axes guessed by default (its redo panel, which shows them, is checked in
    # the window test below: an operator run from Python has no redo panel)
    _select(src)
    assert bpy.ops.apcg.make_target() == {"FINISHED"}
    guessed = bpy.context.active_object
    assert guessed[AXES_KEY]["how"] == "guessed" and guessed.parent == lidar
    assert guessed.apcg_target.range_m == pytest.approx(4500.0)
    # stated in the operator: forward -Y, up Z, the same body as the guess
    _select(src)
    assert bpy.ops.apcg.make_target(guess_axes=False, forward="-Y", up="Z", range_m=2000.0,
                                    type_name="My jet") == {"FINISHED"}
    stated = bpy.context.active_object
    assert stated[AXES_KEY]["how"] == "stated" and stated[TYPE_KEY] == "My jet"
    assert np.abs(_verts(stated) - _verts(guessed)).max() < 1e-5
    assert api.axes_label(stated) == "forward -Y, up Z (stated)"
    # a target, a cloud or a lidar cannot be made a target
    _select(stated)
    with pytest.raises(RuntimeError, match="poll"):  # the panel shows no button for it
        bpy.ops.apcg.make_target()
    with pytest.raises(InputError, match="already is an APCG target"):
        api.make_target(lidar, stated)
    with pytest.raises(InputError, match="not a mesh object"):
        api.make_target(lidar, lidar)
    with pytest.raises(InputError, match="axis 'W' unknown"):
        api.make_target(lidar, src, forward="W", up="Z")


def test_stated_axes_that_contradict_the_shape_are_warned_with_the_fix(scene):
    """Make Target with stated axes the shape contradicts (the box jet's nose is -Y, stated
    X): one warning naming the fix in the add-on's words; a right statement, none."""
    src = box.add_box_aircraft()
    lidar = api.add_lidar()
    wrong = api.make_target(lidar, src, 4500.0, forward="X", up="Z")
    warning = wrong[AXES_KEY]["warning"]
    assert "\n" not in warning and "use Forward -Y" in warning and "Guess axes" in warning
    assert "stated: forward X, up Z" in warning
    right = api.make_target(lidar, src, 4500.0, forward="-Y", up="Z")
    assert "warning" not in right[AXES_KEY]
    _select(src)  # the operator too: it finishes, and reports the warning
    assert bpy.ops.apcg.make_target(guess_axes=False, forward="X", up="Z") == {"FINISHED"}
    assert "use Forward -Y" in bpy.context.active_object[AXES_KEY]["warning"]


def test_the_guess_without_scipy_equals_the_guess_with_it(monkeypatch):
    """Blender's own Python has no scipy: the core's guess then finds nearest neighbours with
    numpy, and must give the same answer."""
    import sys

    from apcg_core.catalog.checks import guess_axes, nearest_distance
    v, f = box.box_mesh()
    meshes = [Mesh(v, f)]
    cat = default_catalog()
    for name, (fwd, up) in (("A320neo", ("-Y", "Z")), ("F-16C Fighting Falcon", ("Z", "Y")),
                            ("H135", ("X", "-Z")), ("Matrice 300 RTK", ("Y", "X"))):
        m = cat.mesh(name)
        meshes.append(m.transformed(np.linalg.inv(axis_matrix(fwd, up))))
    with_scipy = [guess_axes(m) for m in meshes]
    rng = np.random.default_rng(0)
    pts, probe = rng.random((300, 3)), rng.random((200, 3))
    fast = nearest_distance(pts, probe)
    monkeypatch.setitem(sys.modules, "scipy.spatial", None)  # import fails, as in Blender
    np.testing.assert_allclose(nearest_distance(pts, probe), fast, atol=1e-9)
    for m, a in zip(meshes, with_scipy, strict=True):
        b = guess_axes(m)
        assert (a.forward, a.up, a.confident) == (b.forward, b.up, b.confident)


def test_scan_of_a_made_target_equals_the_embree_simulator(scene):
    """The made target scanned in Blender (Geometry Nodes ray casting) gives the cloud the
    embree simulator gives on the box aircraft built without Blender, at the same pose. The
    source object sits between the lidar and the target: being the same aircraft, it hides
    nothing."""
    from blender_addon.objects import lidar_params, simulator_row
    from dataset_builder.simulate import Simulator
    src = box.add_box_aircraft(location=(0.0, 20.0, 1.0))
    lidar = api.add_lidar()
    target = api.make_target(lidar, src, **POSE)
    (cloud,) = api.scan(lidar, quantize=False)
    got, info = api.cloud_from_object(cloud)
    assert info["meta"]["occluded_points"] == 0 and info["meta"]["type"] == "Box jet"
    with Simulator("embree", lidar_params(lidar), quantize=False) as sim:
        ref = sim.simulate(_expected_body(), simulator_row(target)).cloud
    assert len(ref) > 200
    ka = {(int(w), int(h)): r
          for w, h, r in zip(got.cell_w, got.cell_h, got.range_m, strict=True)}
    kb = {(int(w), int(h)): r
          for w, h, r in zip(ref.cell_w, ref.cell_h, ref.range_m, strict=True)}
    common = set(ka) & set(kb)
    assert len(common) / len(set(ka) | set(kb)) >= 0.995  # edge rays may differ
    assert max(abs(ka[k] - kb[k]) for k in common) < 2e-3
    # quantized, as the Scan button does: the same cells
    (q,) = api.scan(lidar, targets=[target])
    assert len(api.cloud_from_object(q)[0]) == len(got)
    # the source object does stand in the way: as any other object it would hide the target
    del target[SOURCE_KEY]
    (hidden,) = api.scan(lidar, targets=[target])
    assert api.cloud_from_object(hidden)[1]["meta"]["occluded_points"] > 0.5 * len(got)


def _a320_object(name="A320neo"):
    """The catalog's A320neo mesh as a scene object with its nose along -Y (as an artist's
    file might have it)."""
    m = default_catalog().mesh("A320neo").transformed(np.linalg.inv(axis_matrix("-Y", "Z")))
    me = bpy.data.meshes.new(name)
    me.from_pydata(m.vertices.tolist(), [], m.faces.tolist())
    me.update()
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def test_generate_where_the_model_knows_the_type(scene):
    lidar = api.add_lidar()
    own = api.make_target(lidar, box.add_box_aircraft(), **GEN_POSE)
    with pytest.raises(InputError) as err:
        api.generate(own)
    msg = str(err.value)
    assert "does not know the type 'Box jet'" in msg
    assert "apcg teach --model" in msg and "--type 'Box jet'" in msg and "Add to" in msg
    _select(own)
    with pytest.raises(RuntimeError, match="does not know the type 'Box jet'"):
        bpy.ops.apcg.generate()
    assert not [o for o in bpy.data.objects if api.is_cloud(o)]  # refused before any work
    # the catalog's own A320neo as a scene object: the model knows the type by its name
    made = api.make_target(lidar, _a320_object(), **GEN_POSE, forward="-Y", up="Z")
    cat = default_catalog()
    assert made[TYPE_KEY] == "A320neo"
    assert made[LENGTH_KEY] == pytest.approx(cat.depth_length_m("A320neo"))
    body = _verts(made)
    assert np.abs(body - cat.mesh("A320neo").vertices).max() < 1e-3  # the catalog's frame
    ref_target = api.add_aircraft(lidar, "A320neo", **GEN_POSE)
    model = api.load_model()
    got, _ = api.cloud_from_object(api.generate(made, model, count=2, seed=5))
    ref, _ = api.cloud_from_object(api.generate(ref_target, model, count=2, seed=5))
    assert len(got) > 0 and len(got) == len(ref)
    assert np.abs(got.xyz - ref.xyz).max() < 1e-4
    _select(made)
    assert bpy.ops.apcg.generate() == {"FINISHED"}


def test_add_to_catalog_for_the_command_line(scene, tmp_path):
    from blender_addon.ops import _type_items
    lidar = api.add_lidar()
    target = api.make_target(lidar, box.add_box_aircraft(), **POSE)
    n_items = len(_type_items(None, None))
    t = api.add_to_catalog(target, "aircraft", "user")
    assert t.name == "Box jet" and t.length_m == pytest.approx(30.0, abs=1e-4)
    assert t.source.startswith("Blender object 'Box jet'")
    names = [item[0] for item in _type_items(None, None)]
    assert len(names) == n_items + 1 and names[-1] == "Box jet"  # the Add Aircraft menu
    env = dict(os.environ, APCG_DATA_DIR=str(tmp_path / "data"))
    r = subprocess.run([*APCG, "catalog", "list", "--json"], capture_output=True, text=True,
                       env=env)
    assert r.returncode == 0, r.stderr
    rows = {row["name"]: row for row in json.loads(r.stdout)}
    assert rows["Box jet"]["length_m"] == pytest.approx(30.0, abs=1e-4)
    assert rows["Box jet"]["span_m"] == pytest.approx(28.0, abs=1e-4)
    # the new type is a catalog type now: Add Aircraft places it, from the saved mesh
    assert bpy.ops.apcg.add_aircraft(type_name="Box jet", range_m=3000.0) == {"FINISHED"}
    again = bpy.context.active_object
    assert np.ptp(_verts(again), axis=0) == pytest.approx([30.0, 28.0, 7.5], abs=1e-4)
    _select(target)
    with pytest.raises(RuntimeError, match="a type named 'Box jet' already exists"):
        bpy.ops.apcg.add_to_catalog()


def test_add_to_catalog_refuses_an_implausible_size_unless_forced(scene, tmp_path):
    lidar = api.add_lidar()
    src = box.add_box_aircraft(name="Tiny drone in mm")
    src.scale = [s * 1000 / 7.5 for s in box.SCALE]  # 4000 x 3733 x 1000 units: millimetres
    target = api.make_target(lidar, src, 5000.0)
    _select(target)
    with pytest.raises(RuntimeError) as err:
        bpy.ops.apcg.add_to_catalog(kind="drone", category="multirotor_drone")
    msg = str(err.value)
    assert "4000 m across, implausible for a drone" in msg and "millimetres" in msg
    assert "tick Force" in msg
    assert "Tiny drone in mm" not in default_catalog().names()
    assert bpy.ops.apcg.add_to_catalog(kind="drone", category="multirotor_drone",
                                       force=True) == {"FINISHED"}
    assert "Tiny drone in mm" in default_catalog().names()
    env = dict(os.environ, APCG_DATA_DIR=str(tmp_path / "data"))
    r = subprocess.run([*APCG, "catalog", "list", "--json"], capture_output=True, text=True,
                       env=env)
    assert "Tiny drone in mm" in {row["name"] for row in json.loads(r.stdout)}


# --- in a real Blender window ---------------------------------------------------------------

@pytest.fixture
def big_display():
    with virtual_display("1600x900") as num:
        yield num


def test_make_target_and_scan_in_a_window(tmp_path, big_display):
    """Make Target (a click on the panel's button) and Scan in a real Blender window (Debian's
    Blender 3.4, the legacy add-on): the redo panel and the APCG panel show the guessed axes.
    With APCG_WRITE_DOCS=1 the screenshot is docs/addon_make_target.png."""
    png = (ROOT / "docs" / "addon_make_target.png" if os.environ.get("APCG_WRITE_DOCS") == "1"
           else tmp_path / "make_target.png")
    rep = run_in_window(tmp_path, big_display, "addon_make_target_script.py", str(png),
                        env_extra={"APCG_DATA_DIR": str(tmp_path / "data")})
    assert rep["make_target"] == ["FINISHED"] and rep["scan"] == ["FINISHED"]
    assert rep["axes"] == "forward -Y, up Z (guessed)"
    assert rep["extents"] == pytest.approx([box.LENGTH_M, box.SPAN_M, box.HEIGHT_M], abs=1e-3)
    assert rep["cloud_points"] > 200 and rep["source_untouched"]
    # a click on the panel's button ran it from the UI: its redo panel shows the guess
    assert rep["clicked"]
    assert rep["redo_axes"] == ["-Y", "Z", True, "axes: forward -Y, up Z (guessed)"]
    assert png.exists() and png.stat().st_size > 50_000


def test_add_to_catalog_keeps_a_reflectivity_and_scans_use_it(scene, tmp_path):
    """The add-on sets a type's reflectivity (SPEC section 8): the catalog stores it, the
    command line lists it, and a scan with a sensor records it in the cloud's metadata."""
    lidar = api.add_lidar()
    target = api.make_target(lidar, box.add_box_aircraft(name="White box"), **POSE)
    t = api.add_to_catalog(target, "aircraft", "user", reflectivity=0.8)
    assert t.reflectivity == pytest.approx(0.8) and target["apcg_reflectivity"] == 0.8
    env = dict(os.environ, APCG_DATA_DIR=str(tmp_path / "data"))
    r = subprocess.run([*APCG, "catalog", "list", "--json"], capture_output=True, text=True,
                       env=env)
    rows = {row["name"]: row for row in json.loads(r.stdout)}
    assert rows["White box"]["reflectivity"] == pytest.approx(0.8)
    assert rows["A320neo"]["reflectivity"] == pytest.approx(0.6)  # its category's default
    (cloud,) = api.scan(lidar, sensor="1064nm-night", seed=2)
    assert api.cloud_from_object(cloud)[1]["meta"]["reflectivity"] == pytest.approx(0.8)
    with pytest.raises(Exception, match="reflectivity"):
        api.add_to_catalog(target, "aircraft", "user", name="Too white", reflectivity=1.7)
