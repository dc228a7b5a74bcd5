"""Model files of every accepted format, each at the unit and axes it declares.

The files are made here: by Blender's own exporters (FBX, .blend, USD, Alembic, glTF) in a
separate bpy process, and by hand where a format's unit or axis must be set exactly (COLLADA in
inches, USD in inches). One test aircraft, modelled the Blender way (nose toward -Y, top +Z):
a 10 m fuselage, a 12 m wing made by a Mirror modifier, and a fin at the tail, plus a light, a
camera and an empty that the import must skip.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from apcg_core.catalog import Catalog
from apcg_core.catalog.checks import check_size, guess_axes, hole_entry_share, size_problem
from apcg_core.catalog.formats import FORMATS, SUFFIXES, collada_asset, read_model
from apcg_core.catalog.importer import import_model
from apcg_core.catalog.mesh import Mesh
from apcg_core.errors import InputError

APCG = str(Path(sys.executable).parent / "apcg")
LENGTH, SPAN, HEIGHT = 10.0, 12.0, 3.0  # fuselage 10 m; wing 12 m; fuselage bottom to fin top

MAKE = r"""
import sys, bpy
out = sys.argv[1]
def scene(scale_length, system="METRIC"):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    u = bpy.context.scene.unit_settings
    u.system, u.scale_length = system, scale_length
    k = 1.0 / scale_length  # model units per metre
    def box(name, size, loc):
        bpy.ops.mesh.primitive_cube_add(size=1.0, location=[c * k for c in loc])
        o = bpy.context.active_object
        o.name = o.data.name = name  # USD names the object after its mesh
        o.scale = [s * k for s in size]
        return o
    box("Fuselage", (1.0, 10.0, 1.0), (0, 0, 0))
    wing = box("Wing", (6.0, 2.0, 0.2), (3.0, 0, 0))   # the right half ...
    wing.location.x = 0.0
    bpy.ops.object.transform_apply(location=False, rotation=False, scale=True)
    for v in wing.data.vertices:   # ... moved to x in [0, 6]; the mirror makes the left half
        v.co.x += 3.0 * k
    wing.modifiers.new("mirror", "MIRROR")
    box("Fin", (0.2, 1.5, 2.0), (0, 4.25, 1.5))        # tail at +Y, top at +2.5 m
    bpy.ops.object.light_add(type="POINT", location=(0, 0, 20 * k))
    bpy.ops.object.camera_add(location=(0, -30 * k, 5 * k))
    bpy.ops.object.empty_add(location=(0, 0, 0))
scene(1.0)
bpy.ops.export_scene.gltf(filepath=out + "/plane.glb", export_format="GLB", export_apply=True)
bpy.ops.export_scene.gltf(filepath=out + "/plane.gltf", export_format="GLTF_SEPARATE",
                          export_apply=True)
bpy.ops.wm.usd_export(filepath=out + "/plane.usdc")
bpy.ops.wm.usd_export(filepath=out + "/plane.usdz")
bpy.ops.wm.alembic_export(filepath=out + "/plane.abc", as_background_job=False)
scene(0.01)
bpy.ops.export_scene.fbx(filepath=out + "/plane_cm.fbx", apply_unit_scale=True,
                         apply_scale_options="FBX_SCALE_NONE")
scene(0.001)
bpy.ops.wm.save_as_mainfile(filepath=out + "/plane_mm.blend")
"""

# COLLADA in inches, Z up, by hand: the test aircraft as three boxes (no modifier in COLLADA).
_BOXES = [("Fuselage", (1.0, 10.0, 1.0), (0, 0, 0)), ("Wing", (12.0, 2.0, 0.2), (0, 0, 0)),
          ("Fin", (0.2, 1.5, 2.0), (0, 4.25, 1.5))]


def _box(size, loc):
    c = np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)])
    v = c * size + loc
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def _collada(unit_m: float, unit_name: str, up: str, to_file) -> str:
    """A COLLADA file of the test aircraft; ``to_file`` maps Blender-style xyz to file axes."""
    geoms, nodes = [], []
    for name, size, loc in _BOXES:
        v, f = _box(np.array(size), np.array(loc))
        v = to_file(v) / unit_m
        pos = " ".join(f"{x:.9g}" for x in v.ravel())
        idx = " ".join(str(i) for i in f.ravel())
        geoms.append(f"""<geometry id="{name}-mesh" name="{name}"><mesh>
<source id="{name}-pos"><float_array id="{name}-arr" count="{v.size}">{pos}</float_array>
<technique_common><accessor source="#{name}-arr" count="{len(v)}" stride="3">
<param name="X" type="float"/><param name="Y" type="float"/><param name="Z" type="float"/>
</accessor></technique_common></source>
<vertices id="{name}-vtx"><input semantic="POSITION" source="#{name}-pos"/></vertices>
<triangles count="{len(f)}"><input semantic="VERTEX" source="#{name}-vtx" offset="0"/>
<p>{idx}</p></triangles></mesh></geometry>""")
        nodes.append(f'<node id="{name}" name="{name}"><instance_geometry url="#{name}-mesh"/>'
                     "</node>")
    unit = f'<unit meter="{unit_m}" name="{unit_name}"/>' if unit_name else ""
    axis = f"<up_axis>{up}</up_axis>" if up else ""
    return f"""<?xml version="1.0" encoding="utf-8"?>
<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">
<asset>{unit}{axis}</asset>
<library_geometries>{''.join(geoms)}</library_geometries>
<library_visual_scenes><visual_scene id="Scene" name="Scene">{''.join(nodes)}</visual_scene>
</library_visual_scenes><scene><instance_visual_scene url="#Scene"/></scene></COLLADA>"""


# A USD stage in inches, Y up, by hand (USD's fallback unit is the centimetre: this one says).
_USDA = """#usda 1.0
(
    metersPerUnit = 0.0254
    upAxis = "Y"
)
def Mesh "Fuselage"
{{
    int[] faceVertexCounts = [{counts}]
    int[] faceVertexIndices = [{indices}]
    point3f[] points = [{points}]
}}
def Camera "Camera"
{{
}}
"""


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("formats")
    proc = subprocess.run([sys.executable, "-c", MAKE, str(out)], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    # Blender-style xyz -> COLLADA Z_UP: the same axes; -> Y_UP: x, z, -y (Y is up).
    (out / "plane_in.dae").write_text(_collada(0.0254, "inch", "Z_UP", lambda v: v))
    (out / "plane_yup_cm.dae").write_text(
        _collada(0.01, "centimeter", "Y_UP", lambda v: v[:, [0, 2, 1]] * [1, 1, -1]))
    v, f = _box(np.array([1.0, 10.0, 1.0]), np.zeros(3))
    v = v[:, [0, 2, 1]] * [1, 1, -1] / 0.0254  # Y up, in inches
    (out / "fuselage_in.usda").write_text(_USDA.format(
        counts=", ".join(["3"] * len(f)), indices=", ".join(str(i) for i in f.ravel()),
        points=", ".join(f"({a:.9g}, {b:.9g}, {c:.9g})" for a, b, c in v)))
    return out


def _is_test_aircraft(mesh: Mesh) -> None:
    """Length 10 m along x, span 12 m along y, fin aft and on top: nose +x, up +z."""
    np.testing.assert_allclose(mesh.extents, [LENGTH, SPAN, HEIGHT], rtol=1e-5, atol=1e-5)
    v = mesh.vertices
    top = v[v[:, 2] > v[:, 2].max() - 0.1]
    assert top[:, 0].mean() < mesh.bounds[:, 0].mean() - 3.0  # the fin is at the tail


# Every file made by Blender's exporters imports at its declared unit, with no option.
@pytest.mark.parametrize("name,unit_words", [
    ("plane.glb", "glTF"), ("plane.gltf", "glTF"), ("plane_cm.fbx", "FBX"),
    ("plane_mm.blend", "unit scale 0.001"), ("plane.usdc", "USD"), ("plane.usdz", "USD"),
    ("plane.abc", "metres assumed")])
def test_blender_exported_files_import_at_their_unit(files, name, unit_words):
    # Blender's convention is nose -Y; glTF declares its own front (+Z, from Blender's -Y)
    forward = None if name.endswith((".glb", ".gltf")) else "-Y"
    mesh, rep = import_model(files / name, forward=forward)
    _is_test_aircraft(mesh)
    assert unit_words in rep.unit
    assert sorted(rep.objects) == ["Fin", "Fuselage", "Wing"], rep.objects
    skipped = " ".join(rep.skipped)
    if not name.endswith((".glb", ".gltf")):  # glTF exports no light or camera by default
        assert "camera" in skipped, rep.skipped
    if name.endswith((".fbx", ".blend", ".usdc")):  # Alembic keeps a light as an empty
        assert "light" in skipped, rep.skipped


def test_glb_axes_come_from_the_file(files):
    _, rep = import_model(files / "plane.glb")
    assert rep.axes == "forward Z (the file), up Y (the file)"
    wrong, _ = import_model(files / "plane.glb", forward="X", up="Z")  # overriding is obeyed
    assert not np.allclose(wrong.extents, [LENGTH, SPAN, HEIGHT], atol=1e-3)


def test_mirror_modifier_is_applied(files):
    # without the modifier the wing would be 6 m: the span proves the evaluated mesh was taken
    mesh, _ = import_model(files / "plane_mm.blend", forward="-Y", objects="Wing")
    assert mesh.extents[1] == pytest.approx(SPAN, rel=1e-6)


def test_objects_pattern_picks_objects(files):
    mesh, rep = import_model(files / "plane.usdc", forward="-Y", objects="Fus*,Wing")
    assert sorted(rep.objects) == ["Fuselage", "Wing"]
    assert mesh.extents[2] == pytest.approx(1.0, rel=1e-5)  # no fin: the fuselage's height
    with pytest.raises(InputError, match="Blender could not import it.*no object"):
        import_model(files / "plane.usdc", objects="Rotor*")
    with pytest.raises(InputError, match="no surface to take"):
        import_model(files / "plane_in.dae", objects="Rotor*")


def test_collada_declaring_inches_imports_at_the_right_size(files):
    assert collada_asset(files / "plane_in.dae") == (0.0254, "inch", "Z")
    mesh, rep = import_model(files / "plane_in.dae", forward="-Y")
    _is_test_aircraft(mesh)
    assert 'meter="0.0254" name="inch"' in rep.unit and rep.scale == 0.0254
    # Y_UP in centimetres: up and unit come from the file; the nose (Blender's -Y) is the
    # file's +Z, stated
    mesh, rep = import_model(files / "plane_yup_cm.dae", forward="Z")
    assert rep.axes == "forward Z (given), up Y (the file)" and rep.scale == 0.01
    _is_test_aircraft(mesh)
    # an option overrides the declared unit
    mesh, rep = import_model(files / "plane_in.dae", forward="-Y", unit_scale=1.0)
    assert mesh.extents[0] == pytest.approx(LENGTH / 0.0254, rel=1e-6)


MAKE_34 = r"""
import bpy, sys
out = sys.argv[sys.argv.index("--") + 1]
bpy.ops.wm.read_factory_settings(use_empty=True)
u = bpy.context.scene.unit_settings
u.system, u.scale_length = "METRIC", 0.01
bpy.ops.mesh.primitive_cube_add(size=1.0)
bpy.context.active_object.scale = (400, 200, 100)   # 4 x 2 x 1 m, in centimetres
bpy.ops.object.light_add(type="POINT")
bpy.ops.wm.collada_export(filepath=out)
"""


def test_collada_from_blenders_own_exporter(tmp_path, blender_binary):
    """Blender 3.4 (the last with COLLADA) writes the scene's unit: centimetres here."""
    script, dae = tmp_path / "make.py", tmp_path / "box_cm.dae"
    script.write_text(MAKE_34)
    proc = subprocess.run([blender_binary, "-b", "--factory-startup", "--python-exit-code", "1",
                           "-P", str(script), "--", str(dae)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0 and dae.exists(), proc.stderr[-2000:]
    mesh, rep = import_model(dae)
    np.testing.assert_allclose(mesh.extents, [4.0, 2.0, 1.0], rtol=1e-6)
    assert rep.scale == 0.01 and "centimeter" in rep.unit


def test_usd_declaring_inches_and_y_up(files):
    mesh, rep = import_model(files / "fuselage_in.usda", forward="-Y")
    np.testing.assert_allclose(mesh.extents, [10.0, 1.0, 1.0], rtol=1e-5)
    assert rep.objects == ["Fuselage"] and any("camera" in s for s in rep.skipped)


def test_the_blender_binary_reads_fbx_too(files, monkeypatch, blender_binary):
    """Without bpy in this Python the Blender-read formats go through `blender -b`."""
    monkeypatch.setenv("APCG_BLENDER", blender_binary)
    mesh, rep = import_model(files / "plane_cm.fbx", forward="-Y")
    _is_test_aircraft(mesh)


def test_a_blender_import_past_its_time_is_stopped_with_one_line(files, monkeypatch,
                                                                 blender_binary):
    """No import waits for ever on Blender: past $APCG_BLENDER_TIMEOUT_S its process is killed
    and the file named. (10 ms: Blender's start-up alone takes a hundred times that.)"""
    monkeypatch.setenv("APCG_BLENDER", blender_binary)
    monkeypatch.setenv("APCG_BLENDER_TIMEOUT_S", "0.01")
    with pytest.raises(InputError, match=r"plane_cm\.fbx: Blender did not finish importing it "
                                         r"within 0\.01 s \(\$APCG_BLENDER_TIMEOUT_S\)"):
        import_model(files / "plane_cm.fbx", forward="-Y")
    for bad in ("soon", "0", "-5", "inf", "nan"):
        monkeypatch.setenv("APCG_BLENDER_TIMEOUT_S", bad)
        with pytest.raises(InputError, match=f"APCG_BLENDER_TIMEOUT_S '{bad}' not accepted"):
            import_model(files / "plane_cm.fbx", forward="-Y")


def test_format_table_is_one_table():
    assert len(SUFFIXES) == len(set(SUFFIXES))
    for s in (".dae", ".fbx", ".blend", ".usd", ".usda", ".usdc", ".usdz", ".abc", ".glb",
              ".gltf", ".obj", ".stl", ".ply", ".off"):
        assert s in SUFFIXES
    assert {f.via for f in FORMATS} == {"own reader", "trimesh", "trimesh + pycollada",
                                        "Blender"}


def test_broken_files_are_named(tmp_path):
    for name, data in (("x.fbx", b"not an fbx at all"), ("x.dae", b"<COLLADA><asset>"),
                       ("x.usda", b"#usda 1.0\n(\n garbage"), ("x.blend", b"BLENDER-v999")):
        p = tmp_path / name
        p.write_bytes(data)
        with pytest.raises(InputError) as e:
            read_model(p)
        assert str(p) in str(e.value)
    d = tmp_path / "dir.obj"
    d.mkdir()
    with pytest.raises(InputError, match="is a directory"):
        read_model(d)


# Sizes: a millimetre model read as metres is refused, with the fix.
def test_size_check_refuses_millimetres_as_metres(files, tmp_path):
    mesh, _ = import_model(files / "plane_in.dae", forward="-Y")
    mm = mesh.transformed(np.eye(3) * 1000.0)
    problem = size_problem(mm.extents, "aircraft")
    assert "12000 m" in problem and "millimetres: --unit-scale 0.001" in problem
    assert size_problem(mesh.extents, "aircraft") is None
    assert "--unit-scale" in size_problem(mesh.extents, "drone")  # 12 m is no drone
    assert size_problem([0.009, 0.005, 0.002], "drone") is not None  # 9 mm drone
    with pytest.raises(InputError, match="implausible for an aircraft"):
        check_size(mm.extents, "aircraft")
    assert check_size(mm.extents, "aircraft", force=True) is not None
    cat = Catalog(user_path=tmp_path)
    with pytest.raises(InputError, match="implausible"):
        cat.add_user_type("huge", mm, "aircraft", "user", "x")
    assert cat.add_user_type("huge", mm, "aircraft", "user", "x", force=True).name == "huge"
    for bad in ("", "  ", "5", "a/b"):
        with pytest.raises(InputError, match="not accepted"):
            cat.add_user_type(bad, mesh, "aircraft", "user", "x")


def _run(*args, env):
    return subprocess.run([APCG, *args], capture_output=True, text=True, timeout=300, env=env)


def test_catalog_add_cli_every_way(files, tmp_path):
    env = {**os.environ, "APCG_DATA_DIR": str(tmp_path / "data")}
    # millimetres as metres: refused with the hint, nothing added
    obj = tmp_path / "plane_mm.obj"
    mesh, _ = import_model(files / "plane_in.dae", forward="-Y")
    from apcg_core.catalog.importer import export_mesh
    export_mesh(mesh.transformed(np.eye(3) * 1000.0), obj)
    bad = _run("catalog", "add", str(obj), "--name", "mm", env=env)
    assert bad.returncode == 2 and "--unit-scale 0.001" in bad.stderr and "Traceback" not in \
        bad.stderr
    ok = _run("catalog", "add", str(obj), "--name", "mm", "--unit-scale", "0.001", env=env)
    assert ok.returncode == 0, ok.stderr
    forced = _run("catalog", "add", str(obj), "--name", "mm-forced", "--force", env=env)
    assert forced.returncode == 0 and "warning" in forced.stderr
    # COLLADA in inches with no scale option, axes as written in the help
    png = tmp_path / "preview.png"
    dae = _run("catalog", "add", str(files / "plane_in.dae"), "--name", "inch-plane",
               "--forward", "-Y", "--preview", str(png), env=env)
    assert dae.returncode == 0, dae.stderr
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    dry = _run("catalog", "add", str(files / "plane_cm.fbx"), "--name", "fbx", "--dry-run",
               env=env)
    assert dry.returncode == 0 and "nothing added" in dry.stdout and "FBX" in dry.stdout
    # the shape tells the nose axis: one warning line with the option that fixes it
    warned = [ln for ln in dry.stderr.splitlines() if "contradict the shape" in ln]
    assert len(warned) == 1 and "use --forward -Y" in warned[0], dry.stderr
    rows = json.loads(_run("catalog", "list", "--json", env=env).stdout)
    names = [r["name"] for r in rows if r["index"] >= 1000]
    assert names == ["mm", "mm-forced", "inch-plane"]
    inch = [r for r in rows if r["name"] == "inch-plane"][0]
    assert inch["length_m"] == pytest.approx(LENGTH, rel=1e-5)
    assert inch["span_m"] == pytest.approx(SPAN, rel=1e-5)


def test_guess_axes_on_the_test_aircraft_and_reference_meshes(files):
    raw = read_model(files / "plane_in.dae").mesh  # file axes: nose -Y, up Z
    g = guess_axes(raw)
    assert (g.forward, g.up, g.confident) == ("-Y", "Z", True)
    from test_import import REF
    for name, forward in (("odedstein_plane.obj", "X"), ("pyvista_airplane.ply", "-Y"),
                          ("px4_believer_body_m.glb", "-X")):
        g = guess_axes(read_model(REF / name).mesh)
        assert (g.forward, g.up) == (forward, "Z"), name


def test_reference_meshes_at_their_declared_unit():
    from test_import import REF
    iris, rep = import_model(REF / "px4_iris.stl")  # STL declares nothing: metres assumed
    assert rep.unit.startswith("not declared") and max(iris.extents) == pytest.approx(0.48,
                                                                                      abs=0.01)
    assert size_problem(iris.extents, "drone") is None
    assert "millimetres" in size_problem(iris.extents * 1000, "drone")
    # the believer's glTF declares metres (but its axes break glTF's convention: stated)
    bel, rep = import_model(REF / "px4_believer_body_m.glb", forward="-X", up="Z")
    assert rep.unit.startswith("glTF") and rep.scale == 1.0
    assert bel.extents[1] == pytest.approx(1.94, abs=0.02)  # "1.94 m span"
    assert size_problem(bel.extents, "drone") is None


def test_hole_share_sees_open_windows():
    import trimesh
    cyl = trimesh.creation.cylinder(radius=2.0, height=40.0, sections=64).subdivide()
    cyl = cyl.subdivide()
    cyl.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    closed = Mesh(np.asarray(cyl.vertices), np.asarray(cyl.faces))
    assert hole_entry_share(closed)["share"] == 0.0
    inverted = Mesh(closed.vertices, closed.faces[:, ::-1])  # winding is not the question
    assert hole_entry_share(inverted)["share"] == 0.0
    c = cyl.triangles_center
    window = (np.abs(c[:, 2] - 0.5) < 0.6) & (np.abs(c[:, 0]) < 18) & (np.abs(c[:, 1]) > 1.5) \
        & (np.sin(c[:, 0] * 2.0) > 0.64)
    assert 50 < window.sum() < 0.05 * len(c)
    windows = hole_entry_share(Mesh(closed.vertices, closed.faces[~window]))
    assert windows["share"] > 0.01
    sheet = Mesh(np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0.0]]),
                 np.array([[0, 1, 2], [0, 2, 3]]))
    seen = hole_entry_share(sheet)  # a plate seen from both sides is not a hole
    assert seen["share"] == 0.0 and seen["sheets"] == 1 and seen["rays_hit"] > 0


def test_open_mesh_warning_in_catalog_add(tmp_path):
    import trimesh
    box = trimesh.creation.box(extents=(20.0, 4.0, 4.0))
    keep = box.triangles_center[:, 2] < 1.9  # no lid: rays from above see the floor inside
    p = tmp_path / "open_box.ply"
    trimesh.Trimesh(box.vertices, box.faces[keep]).export(p)
    env = {**os.environ, "APCG_DATA_DIR": str(tmp_path / "data")}
    out = _run("catalog", "add", str(p), "--name", "tray", "--dry-run", env=env)
    assert out.returncode == 0 and "enter" in out.stderr and "through holes" in out.stderr
