import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from apcg_core.catalog import Catalog
from apcg_core.catalog.importer import EXPORT_SUFFIXES, export_mesh, import_model, read_mesh
from apcg_core.errors import InputError


def _reference_dir() -> Path:
    """The shared reference meshes: $APCG_REFERENCE_MESHES, else ../shared beside the repo."""
    env = os.environ.get("APCG_REFERENCE_MESHES")
    candidates = [Path(env)] if env else []
    candidates += [Path(__file__).resolve().parents[2] / "shared" / "reference" / "meshes",
                   Path("/work/shared/reference/meshes")]
    return next((c for c in candidates if c.is_dir()), candidates[0])


REF = _reference_dir()
APCG = str(Path(sys.executable).parent / "apcg")
CAT = Catalog(include_user=False)

# (file, forward, up): the believer's nose points to the file's -X (its fin sits at +X). The
# PyVista airplane's nose points to -Y (its length is along y, its span along x), although
# ../shared/reference/README.md says "length along x": its three-view drawing shows it.
AIRPLANES = [("odedstein_plane.obj", "X", "Z"), ("pyvista_airplane.ply", "-Y", "Z"),
             ("px4_believer_body_m.glb", "-X", "Z")]


@pytest.fixture(scope="module", autouse=True)
def reference_meshes_present():
    assert REF.is_dir(), f"reference meshes not found at {REF}"


@pytest.mark.parametrize("name,forward,up", AIRPLANES)
def test_reference_airplanes_land_nose_forward_up_up(name, forward, up):
    mesh, rep = import_model(REF / name, forward=forward, up=up, length_m=12.5)
    v = mesh.vertices
    assert mesh.extents[0] == pytest.approx(12.5, rel=1e-12)
    assert rep.extents_m[0] == pytest.approx(12.5, rel=1e-12)
    # the fin (the highest points) is aft of the middle and above the wing
    top = v[v[:, 2] > v[:, 2].max() - 0.03 * mesh.extents[2]]
    mid_x = v[:, 0].min() + 0.5 * mesh.extents[0]
    assert top[:, 0].mean() < mid_x
    # the span is along y (the model is its own mirror image across y) and the aircraft is
    # flat: height is the smallest extent
    assert mesh.extents[2] < mesh.extents[0] and mesh.extents[2] < mesh.extents[1]
    from apcg_core.catalog.checks import _mirror_error
    pts = v[::max(1, len(v) // 4000)]
    assert _mirror_error(pts, 1) < _mirror_error(pts, 0)
    # importing with the opposite forward axis puts the fin forward: the test can fail
    flipped, _ = import_model(REF / name, forward=forward.replace("-", "") if "-" in forward
                              else "-" + forward, up=up, length_m=12.5)
    w = flipped.vertices
    top2 = w[w[:, 2] > w[:, 2].max() - 0.03 * flipped.extents[2]]
    assert top2[:, 0].mean() > w[:, 0].min() + 0.5 * flipped.extents[0]


def test_reference_quadcopter_units_and_up():
    mesh, rep = import_model(REF / "px4_iris.stl", forward="X", up="Z", unit_scale=1.0)
    assert max(mesh.extents[:2]) == pytest.approx(0.48, abs=0.01)  # "0.48 m across"
    assert mesh.extents[2] < min(mesh.extents[:2])
    assert rep.n_bodies > 1 and not rep.watertight and rep.centre == "bounding-box centre"
    np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0, atol=1e-12)


def test_closed_and_multi_body_models_are_reported():
    _, closed = import_model(REF / "odedstein_plane.obj", length_m=37.57)
    assert closed.watertight and closed.n_bodies == 1 and closed.centre == "volume centroid"
    mesh, open_ = import_model(REF / "pyvista_airplane.ply", length_m=37.57)
    assert not open_.watertight and open_.n_bodies == 7
    assert open_.centre == "bounding-box centre"


def _off(tmp_path, text, name="m.off"):
    p = tmp_path / name
    p.write_bytes(text.encode())
    return p


def test_off_modelnet_quirks(tmp_path):
    quad = "0 0 0\r\n1 0 0\r\n1 1 0\r\n0 1 0\r\n0 0 1\r\n"
    faces = "4 0 3 2 1\r\n3 0 1 4\r\n3 1 2 4\r\n3 2 3 4\r\n3 3 0 4\r\n"
    glued = _off(tmp_path, "OFF5 5 0\r\n" + quad + faces, "glued.off")  # ModelNet's first line
    normal = _off(tmp_path, "OFF\n# comment\n5 5 0\n" + quad.replace("\r", "") + faces, "n.off")
    a, b = read_mesh(glued), read_mesh(normal)
    assert len(a.faces) == 6  # the quad was split in two
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    mesh, rep = import_model(glued, length_m=2.0)
    assert rep.watertight and mesh.extents[0] == pytest.approx(2.0)


@pytest.mark.parametrize("content,needle", [
    ("", "empty"),
    ("OFF\n3 1 0\n0 0 0\n1 0 0\n", "declares 3 vertices and 1 faces, the file holds 2 and 0"),
    ("PLY nonsense", "not an OFF file"),
])
def test_broken_off_files(tmp_path, content, needle):
    p = _off(tmp_path, content)
    with pytest.raises(InputError, match=needle) as e:
        read_mesh(p)
    assert str(p) in str(e.value)


def test_broken_other_files(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_mesh(tmp_path / "missing.obj")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nend_header\n\x00")
    with pytest.raises(InputError, match="bad.ply"):
        read_mesh(bad)
    txt = tmp_path / "m.xyz"
    txt.write_text("1 2 3")
    with pytest.raises(InputError, match="unsupported format"):
        read_mesh(txt)
    with pytest.raises(InputError, match="forward 'Z' and up 'Z'"):
        import_model(REF / "odedstein_plane.obj", forward="Z", up="Z", length_m=1)
    with pytest.raises(InputError, match="axis 'W' unknown"):
        import_model(REF / "odedstein_plane.obj", forward="W", length_m=1)


@pytest.mark.parametrize("ext", [s.lstrip(".") for s in EXPORT_SUFFIXES])
@pytest.mark.parametrize("name", ["ATR 72-600", "A320neo"])
def test_export_round_trip(tmp_path, ext, name):
    """Every format `catalog export` writes reads back with `catalog add`'s importer at the
    same size and attitude (glTF: written +Y up, +Z forward as its specification says, read
    back the same way; the others in the body frame's own axes)."""
    m = CAT.mesh(name)
    p = export_mesh(m, tmp_path / f"atr.{ext}")
    back, rep = import_model(p, guess=True)
    assert len(back.vertices) == len(np.unique(m.vertices, axis=0))
    assert len(back.faces) == len(m.faces)
    np.testing.assert_allclose(back.extents, m.extents, rtol=1e-6)
    assert rep.scale == 1.0 and rep.centre == "volume centroid"
    # same vertex set, nose +x, fin up (float32 formats keep ~1e-7 relative): each vertex
    # has the other's within that, both ways (a sort of rounded coordinates would flip where
    # a coordinate sits on a rounding boundary)
    from scipy.spatial import cKDTree
    tol = 2e-6 * np.abs(m.vertices).max()
    assert cKDTree(m.vertices).query(back.vertices)[0].max() <= tol
    assert cKDTree(back.vertices).query(m.vertices)[0].max() <= tol
    from apcg_core.catalog.checks import axes_fix
    assert axes_fix(rep.guess, rep.forward, rep.up) == {}  # the shape agrees: no warning
    assert not list(tmp_path.glob("*.part"))


def test_exported_gltf_is_y_up_z_forward_as_its_specification_says(tmp_path):
    """glTF 2.0: +Y up, +Z forward, +X left (right-handed), metres: stored that way."""
    m = CAT.mesh("A320neo")
    stored = read_mesh(export_mesh(m, tmp_path / "a.glb"))
    ext = stored.extents
    assert ext == pytest.approx([m.extents[1], m.extents[2], m.extents[0]], rel=1e-6)
    nose = stored.vertices[np.argmax(stored.vertices[:, 2])]  # the foremost point, on +Z
    assert abs(nose[0]) < 0.1 * ext[0]  # on the centre line (X is the span)
    fin_top = stored.vertices[np.argmax(stored.vertices[:, 1])]  # the highest point, +Y
    assert fin_top[2] < 0  # the fin lies aft


def test_user_catalog_add_reload_and_refuse(tmp_path):
    cat = Catalog(user_path=tmp_path)
    mesh, _ = import_model(REF / "odedstein_plane.obj", length_m=37.57)
    t = cat.add_user_type("my-plane", mesh, "aircraft", "user", "odedstein_plane.obj")
    assert t.index == 1000 and t.length_m == pytest.approx(37.57)
    again = Catalog(user_path=tmp_path)
    assert again.get("my-plane").index == 1000
    np.testing.assert_array_equal(again.mesh("my-plane").vertices, mesh.vertices)
    assert again.get(3).name == "A320neo"  # built-in indices untouched
    t2 = again.add_user_type("second", mesh, "aircraft", "user", "x")
    assert t2.index == 1001 and Catalog(user_path=tmp_path).get(1001).name == "second"
    with pytest.raises(InputError, match="already exists"):
        again.add_user_type("A320neo", mesh, "aircraft", "user", "x")
    (tmp_path / "user_types.json").write_text("{broken")
    with pytest.raises(InputError, match="damaged"):
        Catalog(user_path=tmp_path)


def _run(*args, env=None):
    return subprocess.run([APCG, *args], capture_output=True, text=True, timeout=300, env=env)


def test_signed_axis_values_are_joined_to_their_option():
    from apcg_core.cli import join_signed_values
    assert join_signed_values(["add", "f.obj", "--forward", "-X", "--up", "-y", "--name", "-X"]) \
        == ["add", "f.obj", "--forward=-X", "--up=-y", "--name", "-X"]
    # only an axis is joined: a following option stays an option
    assert join_signed_values(["--forward", "--up", "Z"]) == ["--forward", "--up=Z"]


def test_catalog_cli(tmp_path):
    env = {**os.environ, "APCG_DATA_DIR": str(tmp_path / "data")}
    out = _run("catalog", "list", "--json", env=env)
    assert out.returncode == 0, out.stderr
    rows = json.loads(out.stdout)
    assert len(rows) == len(CAT)
    for key in ("name", "index", "kind", "category", "length_m", "span_m", "height_m"):
        assert key in rows[0]
    assert {r["kind"] for r in rows} == {"aircraft", "drone"}
    add = _run("catalog", "add", str(REF / "px4_believer_body_m.glb"), "--name", "believer",
               "--forward", "-X", "--up", "Z", "--unit-scale", "1", "--kind", "drone", env=env)
    assert add.returncode == 0, add.stderr
    assert "index 1000" in add.stdout and "96 bodies" in add.stdout
    rows = json.loads(_run("catalog", "list", "--json", env=env).stdout)
    assert rows[-1]["name"] == "believer" and rows[-1]["index"] == 1000
    exp = _run("catalog", "export", "believer", "-o", str(tmp_path / "b.obj"), env=env)
    assert exp.returncode == 0 and (tmp_path / "b.obj").stat().st_size > 0
    sheet = _run("catalog", "show", "H135", "A320neo", "-o", str(tmp_path / "s.png"), env=env)
    assert sheet.returncode == 0, sheet.stderr
    assert (tmp_path / "s.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    bad = _run("catalog", "export", "A380", "-o", str(tmp_path / "x.ply"), env=env)
    assert bad.returncode == 2 and "did you mean A380-800" in bad.stderr


# --- round trips through the command line, axes that contradict the shape, bad meshes ---

@pytest.mark.parametrize("ext", [s.lstrip(".") for s in EXPORT_SUFFIXES])
def test_catalog_export_then_add_gives_the_same_type(tmp_path, ext):
    """`apcg catalog export A320neo -o a.EXT` then `apcg catalog add a.EXT`: the same size and
    attitude, no axes warning (the issue's airliner on its side, for glTF)."""
    env = {**os.environ, "APCG_DATA_DIR": str(tmp_path / "data")}
    f = tmp_path / f"a.{ext}"
    exp = _run("catalog", "export", "A320neo", "-o", str(f), env=env)
    assert exp.returncode == 0, exp.stderr
    add = _run("catalog", "add", str(f), "--name", "round trip", env=env)
    assert add.returncode == 0 and "warning" not in add.stderr, add.stderr
    cat = Catalog(user_path=tmp_path / "data" / "catalog")
    a, b = CAT.mesh("A320neo"), cat.mesh("round trip")
    np.testing.assert_allclose(b.extents, a.extents, rtol=1e-6)
    t = cat.get("round trip")
    assert (t.length_m, t.span_m, t.height_m) == pytest.approx(tuple(a.extents), rel=1e-6)
    sa = a.vertices[np.lexsort(np.round(a.vertices, 3).T)]
    sb = b.vertices[np.lexsort(np.round(b.vertices, 3).T)]
    np.testing.assert_allclose(sb, sa, atol=1e-4)


def _collada(tmp_path, mesh, up_axis: str) -> Path:
    """A COLLADA file of ``mesh``'s vertices as given, declaring ``up_axis``."""
    import trimesh
    data = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(file_type="dae")
    text = (data if isinstance(data, str) else data.decode())
    text = re.sub(r"<up_axis>\w+</up_axis>", f"<up_axis>{up_axis}</up_axis>", text)
    p = tmp_path / f"m_{up_axis}.dae"
    p.write_text(text)
    return p


def _warnings(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ln.startswith("apcg catalog: warning:")]


def test_declared_axes_that_contradict_the_shape_are_warned_with_the_fix(tmp_path):
    """A Y_UP COLLADA whose vertices are Z-up (as many robotics meshes are): one warning line
    naming --up Z; with --up Z, or with vertices that are Y-up, none."""
    env = {**os.environ, "APCG_DATA_DIR": str(tmp_path / "data")}
    body = CAT.mesh("A320neo")
    lying = _collada(tmp_path, body, "Y_UP")  # Z-up vertices declared Y-up
    dry = _run("catalog", "add", str(lying), "--name", "x", "--dry-run", env=env)
    assert dry.returncode == 0, dry.stderr
    warned = _warnings(dry.stderr)
    assert len(warned) == 1 and "use --up Z" in warned[0] and "m_Y_UP.dae" in warned[0]
    assert "up Y (the file)" in warned[0]
    fixed = _run("catalog", "add", str(lying), "--name", "x", "--up", "Z", env=env)
    assert fixed.returncode == 0 and not _warnings(fixed.stderr), fixed.stderr
    assert Catalog(user_path=tmp_path / "data" / "catalog").get("x").length_m == \
        pytest.approx(body.extents[0], rel=1e-6)
    from apcg_core.catalog.importer import axis_matrix
    honest = _collada(tmp_path, body.transformed(axis_matrix("X", "Y").T), "Z_UP")
    honest = honest.rename(tmp_path / "honest.dae")
    text = honest.read_text().replace("<up_axis>Z_UP</up_axis>", "<up_axis>Y_UP</up_axis>")
    honest.write_text(text)  # Y-up vertices, declared Y-up: nothing to say
    ok = _run("catalog", "add", str(honest), "--name", "y", "--dry-run", env=env)
    assert ok.returncode == 0 and not _warnings(ok.stderr), ok.stderr


def test_axes_fix_names_only_what_contradicts_a_confident_guess():
    from apcg_core.catalog.checks import AxesGuess, axes_fix
    from apcg_core.catalog.importer import _default_forward
    g = AxesGuess("X", "Z", "", True)
    assert axes_fix(g, "X", "Y", default_forward=_default_forward) == {"up": "Z"}
    assert axes_fix(g, "Z", "Y") == {"up": "Z", "forward": "X"}  # glTF's declared forward
    assert axes_fix(g, "-X", "Z") == {}  # a sign alone is not contradicted (weaker cue)
    assert axes_fix(g, "Y", "Z") == {"forward": "X"}
    assert axes_fix(g, "X", "Y", up_given=True) == {}  # the user said so
    assert axes_fix(g._replace(confident=False), "X", "Y") == {}
    assert axes_fix(None, "X", "Y") == {}


def _obj(path: Path, vertices, faces) -> Path:
    path.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in vertices)
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
    return path


BOX_V = [[x, y, z] for x in (0.0, 10.0) for y in (0.0, 8.0) for z in (0.0, 2.0)]
BOX_F = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7],
         [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]


def test_degenerate_triangles_are_dropped_with_a_warning(tmp_path):
    """Zero-area triangles (three points on a line, two in one place), here far from the
    model, are dropped with one warning line; the rest is the model, at its own size."""
    env = {**os.environ, "APCG_DATA_DIR": str(tmp_path / "data")}
    v = BOX_V + [[100.0, 0, 0], [200.0, 0, 0], [300.0, 0, 0], [50.0, 50, 50]]
    f = BOX_F + [[8, 9, 10], [8, 8, 11], [0, 1, 1]]
    path = _obj(tmp_path / "degenerate.obj", v, f)
    add = _run("catalog", "add", str(path), "--name", "box", env=env)
    assert add.returncode == 0 and "Traceback" not in add.stderr, add.stderr
    warned = _warnings(add.stderr)
    assert len(warned) == 1 and "3 degenerate (zero-area) triangles dropped" in warned[0]
    t = Catalog(user_path=tmp_path / "data" / "catalog").get("box")
    assert (t.length_m, t.span_m, t.height_m) == pytest.approx((10.0, 8.0, 2.0))
    mesh, rep = import_model(path)
    assert rep.n_dropped == 3 and len(mesh.faces) == 12 and len(mesh.vertices) == 8


@pytest.mark.parametrize("vertices,faces,words", [
    ([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], "its one triangle has zero"),
    ([[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]], [[0, 1, 2], [1, 2, 3]], "zero area"),
    ([[0, 0, 0], [1, 0, "nan"], [0, 1, 0]], [[0, 1, 2]], "non-finite"),
    ([[0, 0, 0], [1, 0, "inf"], [0, 1, 0]], [[0, 1, 2]], "non-finite"),
    ([[0, 0, 0], [1e200, 0, 0], [0, 1e200, 0]], [[0, 1, 2]], "too large"),
])
def test_a_mesh_with_no_surface_is_named_in_one_line(tmp_path, vertices, faces, words):
    path = _obj(tmp_path / "bad.obj", vertices, faces)
    r = _run("catalog", "add", str(path), "--name", "bad", "--dry-run",
             env={**os.environ, "APCG_DATA_DIR": str(tmp_path / "data")})
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "bad.obj" in lines[0] and words in lines[0], r.stderr


def test_an_unknown_preview_format_is_refused_before_any_work(tmp_path):
    env = {**os.environ, "APCG_DATA_DIR": str(tmp_path / "data")}
    missing = tmp_path / "not-read.obj"  # never read: the preview is refused first
    r = _run("catalog", "add", str(missing), "--name", "p", "--preview",
             str(tmp_path / "x.txt"), env=env)
    assert r.returncode == 2 and "--preview" in r.stderr and "'.txt'" in r.stderr
    assert ".png" in r.stderr and "Traceback" not in r.stderr and "not-read" not in r.stderr
    assert not (tmp_path / "data").exists() and not (tmp_path / "x.txt").exists()
