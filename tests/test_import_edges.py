"""Edge cases of user meshes that imported as the wrong model, or with a message that did not
say what was wrong (docs/IMPORT.md): OBJ negative indices across objects, concave polygons,
duplicate faces and T-junction slivers that made a closed model "open" (and moved its origin),
float32 files far from the origin, the axes guess on symmetric boxes, `--objects` on OBJ
groups, and the messages for files that are not what their suffix says."""

import re
import struct

import numpy as np
import pytest

from apcg_core.catalog import catalog as catalog_module
from apcg_core.catalog.checks import guess_axes, size_problem
from apcg_core.catalog.importer import import_model
from apcg_core.cli import main
from apcg_core.errors import InputError


def _box(x0, y0, z0, x1, y1, z1):
    """8 corners and 6 quads (outward, 1-based) of an axis-aligned box."""
    v = [(x, y, z) for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)]
    quads = [(1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5),
             (2, 6, 8, 4)]
    return v, quads


def _tris(quads):
    return [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]


def _obj(path, blocks, negative=False):
    """An OBJ of several `o` blocks (name, vertices, faces); with ``negative`` each block's
    faces count back from its own vertices (-8..-1), as OBJ allows."""
    lines, before = [], 0
    for name, verts, faces in blocks:
        lines.append(f"o {name}")
        lines += [f"v {x} {y} {z}" for x, y, z in verts]
        n = len(verts)
        lines += ["f " + " ".join(str(i - n - 1 if negative else i + before) for i in f)
                  for f in faces]
        before += n
    path.write_text("\n".join(lines) + "\n")
    return path


FUSELAGE = _box(-10, -1, -1, 10, 1, 1)
WING = _box(-2, -8, -0.2, 2, 8, 0.2)


@pytest.fixture
def add(tmp_path, monkeypatch, capsys):
    """`apcg catalog add ARGS --dry-run` in this process, own catalog: (code, out, err)."""
    monkeypatch.setenv("APCG_DATA_DIR", str(tmp_path / "data"))
    catalog_module.default_catalog.cache_clear()

    def run(*args):
        code = main(["catalog", "add", *map(str, args), "--dry-run"])
        out, err = capsys.readouterr()
        return code, out, err
    yield run
    catalog_module.default_catalog.cache_clear()


# --- 1. OBJ negative indices --------------------------------------------------------------

def test_obj_negative_indices_count_back_from_each_objects_own_vertices(tmp_path):
    blocks = [("Fuselage", FUSELAGE[0], _tris(FUSELAGE[1])), ("Wing", WING[0], _tris(WING[1]))]
    neg = _obj(tmp_path / "neg.obj", blocks, negative=True)
    pos = _obj(tmp_path / "pos.obj", blocks)
    m_neg, r_neg = import_model(neg)
    m_pos, r_pos = import_model(pos)
    assert r_neg.extents_m == pytest.approx((20.0, 16.0, 2.0))
    assert r_neg.n_bodies == 2 and r_neg.watertight
    np.testing.assert_array_equal(m_neg.vertices, m_pos.vertices)
    np.testing.assert_array_equal(m_neg.faces, m_pos.faces)


# --- 2. concave polygons ------------------------------------------------------------------

# an L-shaped prism, 20 x 15 x 3 m; each cap one concave 6-gon whose first corner is convex
L_CAP = [(20, 5), (5, 5), (5, 15), (0, 15), (0, 0), (20, 0)]


def _lprism_polys():
    v = [(x, y, 0.0) for x, y in L_CAP] + [(x, y, 3.0) for x, y in L_CAP]
    bottom = list(range(5, -1, -1))  # seen from below: reversed
    top = list(range(6, 12))
    sides = [[i, (i + 1) % 6, 6 + (i + 1) % 6, 6 + i] for i in range(6)]
    return v, [bottom, top] + sides


def _write_lprism(path):
    v, polys = _lprism_polys()
    if path.suffix == ".obj":
        path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in v)
                        + "".join("f " + " ".join(str(i + 1) for i in p) + "\n"
                                  for p in polys))
    elif path.suffix == ".off":
        path.write_text(f"OFF\n{len(v)} {len(polys)} 0\n"
                        + "".join(f"{x} {y} {z}\n" for x, y, z in v)
                        + "".join(f"{len(p)} " + " ".join(map(str, p)) + "\n" for p in polys))
    else:
        path.write_text("ply\nformat ascii 1.0\n"
                        f"element vertex {len(v)}\nproperty float x\nproperty float y\n"
                        f"property float z\nelement face {len(polys)}\n"
                        "property list uchar int vertex_indices\nend_header\n"
                        + "".join(f"{x} {y} {z}\n" for x, y, z in v)
                        + "".join(f"{len(p)} " + " ".join(map(str, p)) + "\n" for p in polys))
    return path


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".off"])
def test_a_concave_polygon_is_triangulated_inside_itself(tmp_path, suffix):
    mesh, rep = import_model(_write_lprism(tmp_path / f"lprism{suffix}"))
    # true area: two caps of 225 m2 (20 x 15 less the 15 x 10 notch) and the sides
    caps = 2 * (20 * 15 - 15 * 10)
    sides = 3 * (20 + 5 + 15 + 10 + 5 + 15)  # the outline's 70 m, 3 m high
    assert mesh.face_areas.sum() == pytest.approx(caps + sides)
    assert rep.watertight and rep.n_faces == 2 * 4 + 6 * 2


def test_convex_polygons_keep_their_fan(tmp_path):
    """A convex polygon is cut as every reader always did, (0, i, i + 1): the same faces."""
    v, quads = FUSELAGE
    p = tmp_path / "quads.obj"
    p.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in v)
                 + "".join("f " + " ".join(map(str, q)) + "\n" for q in quads))
    mesh, _ = import_model(p)
    assert len(mesh.faces) == 12 and mesh.face_areas.sum() == pytest.approx(
        2 * (20 * 2 + 20 * 2 + 2 * 2))


# --- 3. duplicate faces and T-junction slivers ---------------------------------------------

def _closed_aircraft():
    """A closed, non-symmetric-in-x body: a fuselage box and a fin box on its tail."""
    fv, fq = FUSELAGE
    tv, tq = _box(-10, -0.2, 1, -7, 0.2, 4)
    verts = fv + tv
    faces = _tris(fq) + [tuple(i + 8 for i in f) for f in _tris(tq)]
    return verts, faces


def _write_obj(path, verts, faces):
    path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in verts)
                    + "".join("f {} {} {}\n".format(*f) for f in faces))
    return path


def test_a_duplicated_face_does_not_open_a_closed_mesh(tmp_path, add):
    verts, faces = _closed_aircraft()
    m0, r0 = import_model(_write_obj(tmp_path / "a.obj", verts, faces))
    dup = _write_obj(tmp_path / "dup.obj", verts, faces + [faces[0], faces[5][::-1]])
    m1, r1 = import_model(dup)
    assert r0.watertight and r1.watertight and r1.centre.startswith("volume centroid")
    assert r1.n_duplicates == 2
    np.testing.assert_array_equal(m0.vertices, m1.vertices)
    np.testing.assert_array_equal(m0.faces, m1.faces)
    code, out, err = add(dup, "--name", "dup")
    assert code == 0 and "closed" in out and "2 duplicate triangles" in err


def test_every_face_twice_still_closed(tmp_path):
    verts, faces = _closed_aircraft()
    m0, _ = import_model(_write_obj(tmp_path / "a.obj", verts, faces))
    m1, r1 = import_model(_write_obj(tmp_path / "d.obj", verts, faces + faces))
    assert r1.watertight and r1.n_duplicates == len(faces)
    np.testing.assert_array_equal(m0.vertices, m1.vertices)


def test_an_open_double_sided_sheet_keeps_both_sides(tmp_path):
    """Duplicates are dropped only where that closes the mesh: an open model is as it was."""
    verts, faces = _closed_aircraft()
    faces = faces[2:]  # open: one end of the fuselage missing
    both = faces + [f[::-1] for f in faces]
    m, r = import_model(_write_obj(tmp_path / "two.obj", verts, both))
    assert not r.watertight and r.n_duplicates == 0 and len(m.faces) == len(both)


def test_a_zero_area_triangle_sealing_a_t_junction_keeps_the_mesh_closed(tmp_path):
    """One fuselage edge split at its middle on one side only (a T-junction) and sealed by a
    zero-area triangle: the mesh is closed, its origin the volume centroid, as without."""
    verts, faces = _closed_aircraft()
    m0, r0 = import_model(_write_obj(tmp_path / "a.obj", verts, faces))
    # the fuselage's top face (z = 1): corners 2 (-10,-1,1), 4 (-10,1,1), 8 (10,1,1),
    # 6 (10,-1,1); split its edge 2-6 (y = -1) at the middle (vertex 17) in the top only
    verts = verts + [(0.0, -1.0, 1.0)]
    top = [f for f in faces if all(verts[i - 1][2] == 1 for i in f) and
           all(i <= 8 for i in f)]
    rest = [f for f in faces if f not in top]
    new_top = [(2, 17, 4), (17, 8, 4), (17, 6, 8)]
    # orient like the old top triangles (outward: +z)
    n = np.cross(np.subtract(verts[top[0][1] - 1], verts[top[0][0] - 1]),
                 np.subtract(verts[top[0][2] - 1], verts[top[0][0] - 1]))[2]
    if n < 0:
        new_top = [f[::-1] for f in new_top]
    # the sliver (2, 6, 17) on the edge, wound against the top's new edges 2-17 and 17-6
    sliver = (2, 6, 17) if n > 0 else (2, 17, 6)
    m1, r1 = import_model(_write_obj(tmp_path / "tj.obj", verts, rest + new_top + [sliver]))
    assert r1.n_dropped == 1
    assert r1.watertight and r1.centre.startswith("volume centroid")
    np.testing.assert_allclose(m1.bounds, m0.bounds, atol=1e-9)


# --- 7. float32 far from the origin -------------------------------------------------------

def _binary_stl(path, verts, faces, offset):
    v = np.asarray(verts, np.float64) + offset
    data = bytearray(b"\0" * 80 + struct.pack("<I", len(faces)))
    for f in faces:
        data += struct.pack("<3f", 0, 0, 0)
        for i in f:
            data += struct.pack("<3f", *v[i - 1])
        data += b"\0\0"
    path.write_bytes(bytes(data))
    return path


def test_float32_far_from_the_origin_is_named_once(tmp_path, add):
    verts, faces = _closed_aircraft()
    far = _binary_stl(tmp_path / "utm.stl", verts, faces, (512345.678, 4212345.123, 312.5))
    near = _binary_stl(tmp_path / "near.stl", verts, faces, (0.0, 0.0, 0.0))
    assert import_model(near)[1].precision is None
    rep = import_model(far)[1]
    assert rep.precision is not None and "500 mm" in rep.precision
    code, out, err = add(far, "--name", "utm")
    lines = [ln for ln in err.splitlines() if "32-bit" in ln]
    assert code == 0 and len(lines) == 1 and "move the model to the origin" in lines[0]
    code, out, err = add(near, "--name", "near")
    assert "32-bit" not in err


def test_float64_obj_far_from_the_origin_says_nothing(tmp_path):
    verts, faces = _closed_aircraft()
    far = [(x + 512345.678, y + 4212345.123, z) for x, y, z in verts]
    assert import_model(_write_obj(tmp_path / "far.obj", far, faces))[1].precision is None


# --- 5. the axes guess on symmetric shapes ------------------------------------------------

def test_axes_guess_is_unsure_on_a_box_and_on_tied_extents(tmp_path):
    v, q = _box(-10, -5, -2, 10, 5, 2)
    box, _ = import_model(_write_obj(tmp_path / "box.obj", v, _tris(q)))
    assert not guess_axes(box).confident
    v, q = _box(-1, -1, -5, 1, 1, 5)  # 2 x 2 x 10: x and y tie for the smallest
    rod, _ = import_model(_write_obj(tmp_path / "rod.obj", v, _tris(q)))
    assert not guess_axes(rod).confident


def test_axes_guess_still_confident_on_an_aircraft(tmp_path):
    verts, faces = _closed_aircraft()
    wing_v, wing_q = _box(-1, -8, -0.2, 2, 8, 0.2)
    verts2 = verts + wing_v
    faces2 = faces + [tuple(i + 16 for i in f) for f in _tris(wing_q)]
    mesh, _ = import_model(_write_obj(tmp_path / "ac.obj", verts2, faces2))
    g = guess_axes(mesh)
    assert g.confident and (g.forward, g.up) == ("X", "Z")


# --- 6. --objects on OBJ objects and groups -----------------------------------------------

@pytest.mark.parametrize("keyword", ["o", "g"])
def test_objects_picks_obj_objects_and_groups(tmp_path, keyword):
    blocks = [("Fuselage", FUSELAGE[0], _tris(FUSELAGE[1])), ("Wing", WING[0], _tris(WING[1]))]
    p = _obj(tmp_path / "parts.obj", blocks)
    if keyword == "g":
        p.write_text(p.read_text().replace("o ", "g "))
    _, rep = import_model(p, objects="Wing*")
    assert rep.extents_m == pytest.approx((4.0, 16.0, 0.4))
    assert rep.objects == ["Wing"]
    _, rep = import_model(p, objects="Fuselage")
    assert rep.extents_m == pytest.approx((20.0, 2.0, 2.0))


# --- 8. messages --------------------------------------------------------------------------

@pytest.mark.parametrize("name, data, said", [
    ("text.gltf", b"this is not json\n", "not a glTF file"),
    ("text.glb", b"hello, this is text and no binary glTF\n", "not a binary glTF"),
    ("text.stl", b"this is a text file, 42 bytes long......\n", "not an STL file"),
    ("text.obj", b"hello\nworld\n", "no 'v' (vertex) or 'f' (face) lines"),
    ("verts.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces ('f' lines)"),
])
def test_a_file_that_is_not_its_format_says_so(tmp_path, name, data, said):
    p = tmp_path / name
    p.write_bytes(data)
    with pytest.raises(InputError, match=re.escape(said)) as exc:
        import_model(p)
    assert str(p) in str(exc.value)


def test_a_glb_cut_short_says_how_many_bytes(tmp_path):
    import trimesh
    verts, faces = _closed_aircraft()
    tm = trimesh.Trimesh(np.array(verts, float), np.array(faces) - 1, process=False)
    data = tm.export(file_type="glb")
    p = tmp_path / "cut.glb"
    p.write_bytes(data[:len(data) // 2])
    with pytest.raises(InputError, match=rf"cut short \({len(data) // 2} of {len(data)} bytes"):
        import_model(p)


def test_a_binary_ply_cut_short_says_so(tmp_path):
    import trimesh
    verts, faces = _closed_aircraft()
    tm = trimesh.Trimesh(np.array(verts, float), np.array(faces) - 1, process=False)
    data = tm.export(file_type="ply")
    p = tmp_path / "cut.ply"
    p.write_bytes(data[:-40])
    with pytest.raises(InputError, match="binary PLY cut short"):
        import_model(p)


def test_size_refusal_names_the_file_and_the_drone_kind(tmp_path, add):
    v, q = _box(-0.2, -0.25, -0.05, 0.2, 0.25, 0.05)
    p = _write_obj(tmp_path / "quad.obj", v, _tris(q))
    code, out, err = add(p, "--name", "quad")
    assert code == 2 and str(p) in err and "--kind drone" in err
    assert "--kind drone" in size_problem([0.4, 0.5, 0.1], "aircraft")
    assert add(p, "--name", "quad", "--kind", "drone")[0] == 0


def test_gltf_with_only_up_names_the_files_forward(tmp_path):
    import trimesh
    verts, faces = _closed_aircraft()
    tm = trimesh.Trimesh(np.array(verts, float), np.array(faces) - 1, process=False)
    p = tmp_path / "m.glb"
    p.write_bytes(tm.export(file_type="glb"))
    with pytest.raises(InputError, match="declares forward Z.*give --forward too") as exc:
        import_model(p, up="Z")
    assert str(p) in str(exc.value)


def test_a_ply_comment_holding_end_header_is_no_end_of_its_header(tmp_path):
    """The header ends at a line of its own (io.clouds.ply_header_end, every PLY reader's):
    an exporter's comment that mentions end_header cut the header there, and the concave
    polygons' fix read the wrong properties."""
    p = _write_lprism(tmp_path / "noted.ply")
    text = p.read_text().replace("format ascii 1.0\n",
                                 "format ascii 1.0\ncomment written by end_header-tool 2\n")
    p.write_text(text)
    mesh, rep = import_model(p)
    caps = 2 * (20 * 15 - 15 * 10)
    sides = 3 * (20 + 5 + 15 + 10 + 5 + 15)
    assert mesh.face_areas.sum() == pytest.approx(caps + sides)
    assert rep.watertight
