"""`apcg catalog add` refuses what it cannot take whole, before it says or writes anything:
a file cut short (the counts its header declares, a line broken off), a face naming a missing
vertex, a directory, a flat model, an unknown category, an implausible size (a dry run as the
real add); its warnings carry the command's prefix and no raw numpy warning reaches stderr."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from apcg_core.catalog import catalog as catalog_module
from apcg_core.cli import main

APCG = str(Path(sys.executable).parent / "apcg")
REF = next((p for p in (Path(os.environ.get("APCG_REFERENCE_MESHES", "/nonexistent")),
                        Path(__file__).resolve().parents[2] / "shared" / "reference" / "meshes",
                        Path("/work/shared/reference/meshes")) if p.is_dir()), None)
needs_ref = pytest.mark.skipif(REF is None, reason="shared reference meshes not found")

# a closed tetrahedron-like box aircraft: 3 dimensions, 20 m long
BOX = ("v 0 0 0\nv 20 0 0\nv 0 8 0\nv 0 0 3\n"
       "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")


@pytest.fixture
def add(tmp_path, monkeypatch, capsys):
    """Run `apcg catalog add ARGS` in this process with its own user catalog: (code, stdout,
    stderr lines)."""
    monkeypatch.setenv("APCG_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.chdir(tmp_path)
    catalog_module.default_catalog.cache_clear()

    def run(*args):
        code = main(["catalog", "add", *map(str, args)])
        out, err = capsys.readouterr()
        return code, out, err.strip().splitlines()
    yield run
    catalog_module.default_catalog.cache_clear()


def _refused(result, *words):
    code, out, err = result
    assert code == 2, (out, err)
    assert len(err) == 1 and err[0].startswith("apcg catalog: error: "), err
    for w in words:
        assert w in err[0], err[0]
    assert out == ""  # nothing said before the refusal


def test_a_whole_box_is_taken(add, tmp_path):
    (tmp_path / "box.obj").write_text(BOX)
    code, out, err = add("box.obj", "--name", "Box", "--dry-run")
    assert code == 0, err
    assert "dry run: nothing added" in out


@needs_ref
def test_a_truncated_ascii_ply_names_its_counts(add, tmp_path):
    (tmp_path / "m.ply").write_bytes((REF / "pyvista_airplane.ply").read_bytes()[:60000])
    _refused(add("m.ply", "--name", "TruncPly", "--length-m", "30", "--forward", "-Y"),
             "m.ply: the header declares 2452 faces, the file holds 1656", "truncated")
    assert not (tmp_path / "data").exists()


def test_a_ply_cut_in_its_vertices_and_a_bad_face_index(add, tmp_path):
    head = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
            "property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
            "end_header\n")
    (tmp_path / "v.ply").write_text(head + "0 0 0\n20 0 0\n0 8")
    _refused(add("v.ply", "--name", "V", "--dry-run"),
             "the header declares 4 vertices, the file holds 2", "truncated")
    (tmp_path / "f.ply").write_text(head + "0 0 0\n20 0 0\n0 8 0\n0 0 3\n3 0 1 2\n3 0 1 9\n")
    _refused(add("f.ply", "--name", "F", "--dry-run"), "refers to vertex 9",
             "holds 4 vertices")


def test_an_obj_cut_in_a_face_line_is_truncated(add, tmp_path):
    (tmp_path / "t.obj").write_text(BOX + "f 1 2")
    _refused(add("t.obj", "--name", "T", "--dry-run"),
             "the file ends in the middle of line 9", "'f 1 2'", "truncated")


def test_an_obj_face_past_the_vertices_is_named(add, tmp_path):
    (tmp_path / "i.obj").write_text("v 0 0 0\nv 30 0 0\nv 30 30 1\nf 1 2 9\n")
    _refused(add("i.obj", "--name", "I", "--dry-run"),
             "i.obj, line 4: a face refers to vertex 9, but the file holds 3 vertices")


def test_a_truncated_stl_names_its_triangles(add, tmp_path):
    data = bytearray(84 + 50 * 4)
    data[80:84] = (4).to_bytes(4, "little")
    (tmp_path / "b.stl").write_bytes(bytes(data[:84 + 50 * 2 + 7]))
    _refused(add("b.stl", "--name", "B", "--dry-run"),
             "the header declares 4 triangles, the file holds 2", "truncated")
    (tmp_path / "a.stl").write_text("solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\n")
    _refused(add("a.stl", "--name", "A", "--dry-run"), "without its closing 'endsolid'",
             "truncated")


def test_a_directory_is_named_as_one(add, tmp_path):
    _refused(add(".", "--name", "P"), "is a directory")


def test_one_degenerate_triangle_is_counted_as_one(add, tmp_path):
    (tmp_path / "d.obj").write_text("v 0 0 0\nv 0 0 0\nv 1 0 0\nf 1 2 3\n")
    _refused(add("d.obj", "--name", "D", "--dry-run"), "its one triangle has zero area")


@pytest.mark.parametrize("text", [
    "v 0 0 0\nv 30 0 0\nv 30 30 0\nv 0 30 0\nf 1 2 3\nf 1 3 4\n",  # a flat square
    "v 0 0 0\nv 10 0 0\nv 0 10 0\nf 1 2 3\n",  # one 10 m triangle
    "v 0 0 0\nv 30 0 5\nv 30 30 5\nv 0 30 0\nf 1 2 3\nf 1 3 4\n"])  # flat, tilted
def test_a_flat_model_is_refused_without_raw_warnings(tmp_path, text):
    (tmp_path / "flat.obj").write_text(text)
    for extra in ([], ["--dry-run"]):
        p = subprocess.run([APCG, "catalog", "add", str(tmp_path / "flat.obj"), "--name",
                            "Flat", *extra], capture_output=True, text=True, timeout=300,
                           env={**os.environ, "APCG_DATA_DIR": str(tmp_path / "data")})
        assert p.returncode == 2, p.stderr
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and "the model is flat" in lines[0], p.stderr
        assert "RuntimeWarning" not in p.stderr and p.stdout == ""
    assert not (tmp_path / "data").exists()


def test_an_unknown_category_is_refused_with_the_list(add, tmp_path):
    (tmp_path / "box.obj").write_text(BOX)
    _refused(add("box.obj", "--name", "Box", "--category", "airliner_narowbody"),
             "category 'airliner_narowbody' unknown", "did you mean airliner_narrowbody",
             "accepted: airliner_narrowbody,", ", user")
    assert not (tmp_path / "data").exists()
    code, out, err = add("box.obj", "--name", "Box", "--category", "fighter")
    assert code == 0, err


@pytest.mark.parametrize("dry", [[], ["--dry-run"]])
def test_an_implausible_size_is_refused_before_any_warning(add, tmp_path, dry):
    """A millimetre model: the refusal alone (no axes warning first), a dry run as the real
    add, and the sentence says what --force does."""
    mm = "".join(f"v {x * 1000} {y * 1000} {z * 1000}\n" for x, y, z in
                 [(0, 0, 0), (20, 0, 0), (0, 8, 0), (0, 0, 3)])
    (tmp_path / "m_mm.obj").write_text(mm + "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    _refused(add("m_mm.obj", "--name", "X", "--preview", "p.png", *dry),
             "it is 20000 m across", "--unit-scale 0.001",
             "to add it at this size anyway, give --force (which also replaces")
    assert not (tmp_path / "p.png").exists() and not (tmp_path / "data").exists()


@needs_ref
def test_warnings_carry_the_commands_prefix(add, tmp_path):
    code, out, err = add(REF / "pyvista_airplane.ply", "--name", "PV", "--length-m", "30",
                         "--dry-run")
    assert code == 0, err
    assert err and all(line.startswith("apcg catalog: warning: ") for line in err), err
    assert any("contradict the shape" in line for line in err)
