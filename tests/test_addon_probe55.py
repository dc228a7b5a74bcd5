"""The add-on where a probe (session 55, probe 4) found it wrong: another tool's attributes
through export, Scan Animation of a target whose shape is keyframed, the scene's unit scale in
Make Target, a scaled lidar, a deleted lidar, a cgan model at another lidar, blend-relative
"//" paths, the source of a made target hiding other targets, and Geometry Nodes instances.
Real Blender (the bpy module), no mocks, small scenes."""

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from apcg_core.errors import InputError  # noqa: E402
from apcg_core.io.clouds import read_cloud_attributes  # noqa: E402
from blender_addon import api, clouds  # noqa: E402
from tests.addon_helpers import blender_state  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# what export warns with (UserWarning before it had a class of its own)
ExportWarning = getattr(clouds, "ExportWarning", UserWarning)


@pytest.fixture
def scene(addon_scene):
    return addon_scene


def _cells(obj) -> set:
    c, _ = api.cloud_from_object(obj)
    return {(int(w), int(h)) for w, h in zip(c.cell_w, c.cell_h, strict=True)}


# --- 1: another tool's attributes through export ----------------------------------------------
def _foreign_las(path, n=60):
    laspy = pytest.importorskip("laspy")
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(n, 3)) * 5 + [100, 2000, 50]
    h = laspy.LasHeader(point_format=3, version="1.2")
    h.scales, h.offsets = [0.001] * 3, [0, 0, 0]
    las = laspy.LasData(h)
    las.x, las.y, las.z = xyz.T
    las.intensity = rng.integers(0, 65535, n)
    las.classification = rng.integers(0, 10, n)
    las.red = rng.integers(0, 65535, n)
    las.green = rng.integers(0, 65535, n)
    las.blue = rng.integers(0, 65535, n)
    las.write(path)
    return las


@pytest.mark.parametrize("ext", ["las", "ply", "npz"])
def test_export_keeps_another_tools_attributes(scene, tmp_path, ext):
    src = _foreign_las(tmp_path / "foreign.las")
    obj = api.import_cloud(tmp_path / "foreign.las")
    with warnings.catch_warnings():
        warnings.simplefilter("error", ExportWarning)  # all of them carried: no warning
        out = api.export_cloud(obj, tmp_path / f"out.{ext}")
    _, _, cols = read_cloud_attributes(out)
    for k in ("intensity", "classification", "red", "green", "blue"):
        assert k in cols, k
        assert np.array_equal(np.asarray(cols[k], np.int64), np.asarray(src[k], np.int64)), k
    if ext == "las":
        import laspy
        back = laspy.read(out)
        assert back.point_format.id == 7  # colours: the format that has them
        assert np.array_equal(back.red, src.red)
    # and the re-imported cloud shows them again
    again = api.import_cloud(out, name="again")
    names = {a.name for a in again.data.attributes}
    assert {"intensity", "classification", "red", "Col"} <= names


def test_export_says_in_one_warning_what_a_format_cannot_carry(scene, tmp_path):
    n = 20
    xyz = np.random.default_rng(1).normal(size=(n, 3)) + [0, 500, 0]
    # another tool's cloud: a fractional intensity (LAS's is a 16-bit whole number)
    path = tmp_path / "tool.npz"
    np.savez(path, xyz=xyz, intensity=np.linspace(0, 1, n).astype(np.float32),
             amplitude=np.arange(n, dtype=np.float32))
    obj = api.import_cloud(path)
    with pytest.warns(ExportWarning, match=r"'intensity'.*do not fit LAS's intensity") as got:
        out = api.export_cloud(obj, tmp_path / "out.las")
    assert len(got) == 1
    _, _, cols = read_cloud_attributes(out)
    assert np.array_equal(cols["amplitude"], np.arange(n, dtype=np.float32))  # extra bytes
    # PLY carries both, with no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error", ExportWarning)
        out = api.export_cloud(obj, tmp_path / "out.ply")
    _, _, cols = read_cloud_attributes(out)
    assert np.allclose(cols["intensity"], np.linspace(0, 1, n))


# --- 2: Scan Animation reads each frame's shape ------------------------------------------------
def test_scan_animation_scans_each_frames_shape(scene, tmp_path):
    from apcg_core.scene import load_sequence
    sc = bpy.context.scene
    sc.frame_start, sc.frame_end = 1, 3
    sc.render.fps = 10
    lidar = api.add_lidar()
    jet = api.add_aircraft(lidar, "A320neo", range_m=1500, elevation_deg=3.4, yaw_deg=90)
    m = jet.modifiers.new("bend", "SIMPLE_DEFORM")
    m.deform_method, m.deform_axis = "BEND", "Z"
    m.angle = 0.0
    m.keyframe_insert("angle", frame=1)
    m.angle = 1.5
    m.keyframe_insert("angle", frame=3)
    sc.frame_set(2)  # not the first frame: each frame's shape is its own
    api.scan_animation(lidar, tmp_path / "seq", backend="embree")
    assert sc.frame_current == 2
    seq = list(load_sequence(tmp_path / "seq"))
    got = []
    for f, fr in zip((1, 2, 3), seq, strict=True):
        sc.frame_set(f)
        want = _cells(api.scan(lidar, backend="embree", occlusion=False)[0])
        got.append({(int(w), int(h)) for w, h in zip(fr.cell_w, fr.cell_h, strict=True)})
        assert got[-1] == want, f
    assert got[0] != got[2]  # the shape did change


# --- 3: the scene's unit scale -----------------------------------------------------------------
def test_make_target_applies_the_scenes_unit_scale(scene):
    sc = bpy.context.scene
    sc.unit_settings.system = "METRIC"
    sc.unit_settings.scale_length = 0.001
    bpy.ops.mesh.primitive_cube_add(size=1)
    box = bpy.context.active_object
    box.scale = (40000, 36000, 12000)  # 40 m x 36 m x 12 m as Blender shows it
    bpy.context.view_layer.update()
    t = api.make_target(api.add_lidar(), box, forward="X", up="Z")
    assert list(t["apcg_axes"]["extents_m"]) == pytest.approx([40.0, 36.0, 12.0], rel=1e-6)
    assert api.pose_of(t)["range_m"] == pytest.approx(4500.0)  # a 40 m target's first range
    sc.unit_settings.system = "NONE"  # no unit declared: metres, as the importer takes it
    t2 = api.make_target(api.lidar_of(t), box, 5e5, forward="X", up="Z")
    assert list(t2["apcg_axes"]["extents_m"]) == pytest.approx([40000, 36000, 12000], rel=1e-6)


# --- 5: a scaled lidar ---------------------------------------------------------------------------
@pytest.mark.parametrize("where", ["own", "parent"])
def test_a_scaled_lidar_is_refused(scene, where):
    lidar = api.add_lidar()
    api.add_aircraft(lidar, "A320neo", range_m=4500, elevation_deg=3.4, pitch_deg=2.0)
    if where == "own":
        lidar.scale = (1.0, 1.0, 3.0)
    else:
        rig = bpy.data.objects.new("Rig", None)
        sc = bpy.context.scene
        sc.collection.objects.link(rig)
        rig.scale = (2.0, 2.0, 2.0)
        lidar.parent = rig
    bpy.context.view_layer.update()
    before = blender_state()
    with pytest.raises(InputError, match=r"lidar 'APCG Lidar' has scale \(.*\).*"
                                         r"its (own|parents')\).*scale must be 1"):
        api.scan(lidar)
    assert blender_state() == before
    if where == "own":
        lidar.scale = (1.0, 1.0, 1.0)
    else:
        lidar.parent.scale = (1.0, 1.0, 1.0)
    bpy.context.view_layer.update()
    assert len(api.scan(lidar)[0].data.vertices) > 0


# --- 8: a deleted lidar --------------------------------------------------------------------------
def test_a_deleted_lidar_is_named_not_a_reference_error(scene):
    lidar = api.add_lidar()
    api.add_aircraft(lidar, "A320neo", range_m=4000, elevation_deg=3.4)
    bpy.data.objects.remove(lidar)
    for call in (lambda: api.scan(lidar),
                 lambda: api.add_aircraft(lidar, "A320neo", range_m=4500, elevation_deg=3)):
        with pytest.raises(InputError, match="the lidar given is a deleted Blender object"):
            call()


# --- 7: a cgan model at another lidar -----------------------------------------------------------
def test_generate_refuses_a_cgan_model_at_another_lidar_as_the_cli_does(scene):
    model_dir = ROOT / "apcg_core" / "models" / "cgan"
    if not (model_dir / "model.json").exists():
        pytest.skip("no shipped cgan model")
    lidar = api.add_lidar()
    api.read_lidar_file(lidar, "double-cells")
    jet = api.add_aircraft(lidar, "A320neo", range_m=4500, elevation_deg=3.4, pitch_deg=2.3,
                           yaw_deg=13.2)
    before = blender_state()
    with pytest.raises(InputError, match="draws at the lidar it was trained on only"):
        api.generate(jet, model=model_dir)
    assert blender_state() == before
    jet.select_set(True)
    bpy.context.view_layer.objects.active = jet
    with pytest.raises(RuntimeError, match="draws at the lidar it was trained on only"):
        bpy.ops.apcg.generate(model_dir=str(model_dir))
    assert blender_state() == before


# --- 9: blend-relative paths --------------------------------------------------------------------
def test_export_import_and_sensor_resolve_blend_relative_paths(scene, tmp_path):
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    lidar = api.add_lidar()
    api.add_aircraft(lidar, "A320neo", range_m=4500, elevation_deg=3.4, pitch_deg=2.0)
    cloud = api.scan(lidar)[0]
    bpy.context.view_layer.objects.active = cloud
    assert bpy.ops.apcg.export_cloud(filepath="//out.ply") == {"FINISHED"}
    assert (tmp_path / "out.ply").is_file()
    assert bpy.ops.apcg.import_cloud(filepath="//out.ply") == {"FINISHED"}
    assert len(bpy.context.active_object.data.vertices) == len(cloud.data.vertices)
    lidar.apcg_lidar.sensor = "1550nm-day"
    api.write_lidar_file(lidar, tmp_path / "sensor.toml")
    lidar.apcg_lidar.sensor = "//sensor.toml"
    assert api.sensor_of(lidar).name == "1550nm-day"


# --- 6: the model a target was made from hides no other target ---------------------------------
def test_the_source_of_a_made_target_hides_no_other_target(scene):
    bpy.ops.mesh.primitive_cylinder_add(vertices=24, radius=2, depth=30,
                                        rotation=(0, math.pi / 2, 0))
    obj = bpy.context.active_object
    obj.name = "MyJet"
    t = api.make_target(None, obj)  # a new lidar at the origin, inside MyJet
    lidar = api.lidar_of(t)
    jet = api.add_aircraft(lidar, "A320neo", range_m=3000, elevation_deg=8, azimuth_deg=60)
    seen = api.scan(lidar, [jet])[0]
    bare = api.scan(lidar, [jet], occlusion=False)[0]
    assert len(seen.data.vertices) == len(bare.data.vertices) > 0
    info = api.cloud_from_object(seen)[1]["meta"]
    assert info["occluded_points"] == 0


# --- 4: Geometry Nodes instances ----------------------------------------------------------------
def _instancing_group():
    ng = bpy.data.node_groups.new("inst", "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gi, go = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    iop = ng.nodes.new("GeometryNodeInstanceOnPoints")
    cube = ng.nodes.new("GeometryNodeMeshCube")
    cube.inputs["Size"].default_value = (8, 8, 8)
    ng.links.new(gi.outputs[0], iop.inputs["Points"])
    ng.links.new(cube.outputs[0], iop.inputs["Instance"])
    ng.links.new(iop.outputs[0], go.inputs[0])
    return ng


def test_geometry_nodes_instances_are_taken_as_blender_draws_them(scene):
    bpy.ops.mesh.primitive_plane_add(size=30)
    obj = bpy.context.active_object
    obj.name = "Instanced"
    obj.modifiers.new("GN", "NODES").node_group = _instancing_group()
    bpy.context.view_layer.update()
    t = api.make_target(api.add_lidar(), obj, forward="X", up="Z")  # at 4500 m
    assert len(t.data.polygons) == 4 * 12  # four 8 m cubes on the plane's corners
    assert list(t["apcg_axes"]["extents_m"]) == pytest.approx([38.0, 38.0, 8.0], abs=1e-4)
    assert len(api.scan(api.lidar_of(t), [t])[0].data.vertices) > 0
