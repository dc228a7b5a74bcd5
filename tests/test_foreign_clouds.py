"""Clouds written by other lidar tools: LAS / LAZ of several point formats with extra bytes, PLY
(ascii, binary of both byte orders) with any vertex properties and other elements, read with
their attributes by the core and by the add-on's import; broken files give InputError."""

import subprocess
import sys

import numpy as np
import pytest

from apcg_core.cloud import PointCloud
from apcg_core.errors import InputError
from apcg_core.io.clouds import read_cloud, read_cloud_attributes, write_cloud

laspy = pytest.importorskip("laspy")

SCALE = 0.001
EXTRAS = [("amplitude", np.float32), ("echo_width", np.float64), ("flags", np.uint8),
          ("deviation", np.int16), ("segment", np.uint64)]


def _las(pf: int, n: int = 50, seed: int = 0):
    """A laspy LasData of point format ``pf`` at geographic-size coordinates, with random
    standard values and extra dimensions; and the values set, by name."""
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(point_format=pf, version="1.4" if pf >= 6 else "1.2")
    header.scales = np.array([SCALE] * 3)
    header.offsets = np.array([500_000.0, 4_000_000.0, 100.0])
    header.add_extra_dims([laspy.ExtraBytesParams(k, t) for k, t in EXTRAS] + [
        laspy.ExtraBytesParams("normal", "3f4"),
        laspy.ExtraBytesParams("height", np.int32, scales=np.array([0.25]),
                               offsets=np.array([10.0]))])
    las = laspy.LasData(header)
    xyz = header.offsets + rng.uniform(-2000, 2000, (n, 3))
    las.x, las.y, las.z = xyz.T
    want = {"intensity": rng.integers(0, 65535, n, dtype=np.uint16),
            "return_number": rng.integers(1, 6, n, dtype=np.uint8),
            "number_of_returns": rng.integers(1, 6, n, dtype=np.uint8),
            "classification": rng.integers(0, 32 if pf < 6 else 256, n, dtype=np.uint8),
            "user_data": rng.integers(0, 256, n, dtype=np.uint8),
            "point_source_id": rng.integers(0, 65535, n, dtype=np.uint16),
            "amplitude": rng.normal(size=n).astype(np.float32),
            "echo_width": rng.normal(size=n),
            "flags": rng.integers(0, 256, n, dtype=np.uint8),
            "deviation": rng.integers(-30000, 30000, n, dtype=np.int16),
            "segment": rng.integers(0, 2**40, n, dtype=np.uint64),
            "height": 10.0 + 0.25 * rng.integers(-1000, 1000, n)}
    if pf >= 1:
        want["gps_time"] = 1.3e9 + rng.uniform(0, 1e4, n)
    if pf in (2, 3, 5, 7, 8, 10):
        for c in ("red", "green", "blue"):
            want[c] = rng.integers(0, 65535, n, dtype=np.uint16)
    for k, v in want.items():
        las[k] = v
    normal = rng.normal(size=(n, 3)).astype(np.float32)
    las.normal = normal
    want.update({f"normal_{i}": normal[:, i] for i in range(3)})
    return las, xyz, want


def _check_las(path, xyz, want):
    cloud, meta, attrs = read_cloud_attributes(path)
    back = laspy.read(path)
    assert meta == {} and len(cloud) == len(xyz)
    assert cloud.xyz.dtype == np.float64
    # exactly laspy's scaled coordinates, so within half a scale step of what was written
    assert np.array_equal(cloud.xyz, np.stack([back.x, back.y, back.z], 1))
    assert np.abs(cloud.xyz - xyz).max() <= SCALE / 2 + 1e-9
    assert np.allclose(cloud.range_m, np.linalg.norm(cloud.xyz, axis=1), rtol=0, atol=1e-9)
    assert not {"X", "Y", "Z", "x", "y", "z", "range_m", "cell_w", "cell_h", "sample"} & set(attrs)
    for k, v in want.items():
        assert np.array_equal(attrs[k], v), k
        if k != "height":  # a scaled extra dimension reads as its float values
            assert attrs[k].dtype == np.asarray(v).dtype, k
    return attrs


@pytest.mark.parametrize("pf", [0, 1, 3, 6, 7, 8, 10])
def test_las_of_any_point_format_with_extra_dimensions(tmp_path, pf):
    las, xyz, want = _las(pf, seed=pf)
    path = tmp_path / f"pf{pf}.las"
    las.write(path)
    attrs = _check_las(path, xyz, want)
    # every dimension of the point format is there, standard or extra
    expected = set(las.point_format.dimension_names) - {"X", "Y", "Z", "normal"}
    assert set(attrs) == expected | {"normal_0", "normal_1", "normal_2"}
    assert len(read_cloud(path)[0]) == len(xyz)


def test_laz_compressed(tmp_path):
    las, xyz, want = _las(7, n=300, seed=5)
    path = tmp_path / "c.laz"
    las.write(path)
    assert laspy.read(path).header.are_points_compressed
    _check_las(path, xyz, want)


def test_own_files_read_as_before_and_laz_round_trips(tmp_path):
    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(40, 3)) * 5 + [0, 3000, 200]
    cl = PointCloud(xyz, np.linalg.norm(xyz, axis=1) + 0.01, rng.integers(-9, 9, 40),
                    rng.integers(-9, 9, 40), rng.integers(0, 3, 40))
    for ext in ("ply", "npz", "las", "laz"):
        p = write_cloud(tmp_path / f"own.{ext}", cl, {"k": [1, 2]})
        back, meta, attrs = read_cloud_attributes(p)
        assert meta == {"k": [1, 2]}
        assert np.array_equal(back.cell_w, cl.cell_w) and np.array_equal(back.sample, cl.sample)
        tol = 1e-4 if ext in ("las", "laz") else 0.0
        assert np.abs(back.xyz - cl.xyz).max() <= tol
        assert np.array_equal(back.range_m, cl.range_m)
        # the project's PLY / NPZ hold nothing more; its LAS carries the format's (zero) fields
        if ext in ("ply", "npz"):
            assert attrs == {}
        else:
            assert len(attrs["intensity"]) == 40 and not attrs["intensity"].any()
        c2, m2 = read_cloud(p)
        assert m2 == meta and np.array_equal(c2.xyz, back.xyz)
    assert laspy.read(tmp_path / "own.laz").header.are_points_compressed


# --- PLY written by hand ------------------------------------------------------------------------
N = 6
PROPS = [("x", "f8", "double"), ("y", "f8", "double"), ("z", "f4", "float"),
         ("intensity", "u2", "ushort"), ("red", "u1", "uchar"), ("green", "u1", "uchar"),
         ("blue", "u1", "uchar"), ("nx", "f4", "float"), ("ny", "f4", "float"),
         ("nz", "f4", "float"), ("scalar_Deviation", "i4", "int"), ("label", "i1", "char")]


def _vertices(seed=0):
    rng = np.random.default_rng(seed)
    rec = np.zeros(N, [(n, "<" + t) for n, t, _ in PROPS])
    for n, t, _ in PROPS:
        rec[n] = (rng.uniform(-500, 500, N) if t[0] == "f" else
                  rng.integers(np.iinfo(t).min, np.iinfo(t).max, N))
    return rec


def _header(fmt, before=(), after=(), props=PROPS):
    lines = ["ply", f"format {fmt} 1.0", "comment made by another tool", *before,
             f"element vertex {N}", *[f"property {ply} {n}" for n, _, ply in props], *after,
             "end_header"]
    return ("\n".join(lines) + "\n").encode()


def _ascii_rows(rec):
    return "".join(" ".join(repr(v.item()) for v in row) + "\n" for row in rec).encode()


FACES = ["element face 2", "property list uchar int vertex_indices", "property uchar flag"]


def _check_ply(path, rec):
    cloud, meta, attrs = read_cloud_attributes(path)
    assert meta == {} and len(cloud) == N
    assert np.array_equal(cloud.xyz, np.stack([rec["x"], rec["y"], rec["z"]], 1))
    assert np.array_equal(cloud.range_m, np.linalg.norm(cloud.xyz, axis=1))
    assert list(attrs) == [n for n, _, _ in PROPS[3:]]
    for n, t, _ in PROPS[3:]:
        assert attrs[n].dtype == np.dtype(t) and np.array_equal(attrs[n], rec[n]), n
    return attrs


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_with_any_properties_and_faces_after(tmp_path, fmt):
    rec = _vertices(1)
    faces = {"ascii": b"3 0 1 2 7\n4 0 1 2 3 9\n",
             "binary_little_endian": bytes([3]) + np.arange(3, dtype="<i4").tobytes() + b"\7"
             + bytes([4]) + np.arange(4, dtype="<i4").tobytes() + b"\x09",
             "binary_big_endian": bytes([3]) + np.arange(3, dtype=">i4").tobytes() + b"\7"
             + bytes([4]) + np.arange(4, dtype=">i4").tobytes() + b"\x09"}[fmt]
    endian = ">" if fmt == "binary_big_endian" else "<"
    body = _ascii_rows(rec) if fmt == "ascii" else rec.astype(
        [(n, endian + t) for n, t, _ in PROPS]).tobytes()
    p = tmp_path / f"{fmt}.ply"
    p.write_bytes(_header(fmt, after=FACES) + body + faces)
    attrs = _check_ply(p, rec)
    assert attrs["intensity"].dtype.byteorder in "=|"  # native, whatever the file's order


def test_ply_with_an_element_before_the_vertices(tmp_path):
    rec = _vertices(2)
    cam = ["element camera 1", "property float view_px", "property double focal",
           "property uchar id"]
    cam_bytes = np.array([(1.5, 35.0, 3)], ">f4, >f8, u1").tobytes()
    p = tmp_path / "cam_first.ply"
    p.write_bytes(_header("binary_big_endian", before=cam, after=FACES)
                  + cam_bytes + rec.astype([(n, ">" + t) for n, t, _ in PROPS]).tobytes())
    _check_ply(p, rec)
    # ascii: one line per element, so even elements with lists before the vertices are skipped
    p = tmp_path / "faces_first.ply"
    p.write_bytes(_header("ascii", before=FACES) + b"3 0 1 2 7\n4 0 1 2 3 9\n"
                  + _ascii_rows(rec))
    _check_ply(p, rec)
    # binary: a list before the vertices hides where they start
    p = tmp_path / "bin_faces_first.ply"
    p.write_bytes(_header("binary_little_endian", before=FACES) + b"\3" + bytes(12) + b"\1"
                  + b"\3" + bytes(12) + b"\1" + rec.tobytes())
    with pytest.raises(InputError, match=r"bin_faces_first\.ply.*'face'.*list"):
        read_cloud_attributes(p)


def test_ply_own_properties_from_another_writer(tmp_path):
    """range_m / cell_w / cell_h written by hand in ascii go into the cloud, typed as declared."""
    p = tmp_path / "own.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                  b"property float z\nproperty double range_m\nproperty int cell_w\n"
                  b"property uint8 cell_h\nproperty float32 quality\nend_header\n"
                  b"1 2 3 7.5 -4 9 0.25\r\n4 5 6 8.5 3 250 0.5\r\n")
    cloud, _, attrs = read_cloud_attributes(p)
    assert np.array_equal(cloud.xyz, [[1, 2, 3], [4, 5, 6]])
    assert np.array_equal(cloud.range_m, [7.5, 8.5]) and np.array_equal(cloud.cell_w, [-4, 3])
    assert np.array_equal(cloud.cell_h, [9, 250]) and cloud.sample is None
    assert list(attrs) == ["quality"] and attrs["quality"].dtype == np.float32


# --- broken files -------------------------------------------------------------------------------
def _raises(path, match):
    with pytest.raises(InputError, match=match) as info:
        read_cloud_attributes(path)
    assert path.name in str(info.value)


def test_broken_files_name_the_file_and_the_problem(tmp_path):
    rec = _vertices(3)
    good = _header("binary_big_endian") + rec.astype([(n, ">" + t) for n, t, _ in PROPS]
                                                     ).tobytes()
    (tmp_path / "short.ply").write_bytes(good[:-1])
    _raises(tmp_path / "short.ply", "truncated")
    rows = _ascii_rows(rec)
    (tmp_path / "short_ascii.ply").write_bytes(_header("ascii") + rows[: rows.rindex(b" ")])
    _raises(tmp_path / "short_ascii.ply", "truncated or malformed")
    # a row broken over two lines: the last vertex's values are missing
    (tmp_path / "lines.ply").write_bytes(_header("ascii") + rows.replace(b" ", b"\n", 1))
    _raises(tmp_path / "lines.ply", "truncated or malformed")
    first = rows.split(b" ", 1)[0]
    (tmp_path / "word.ply").write_bytes(_header("ascii") + rows.replace(first, b"oops", 1))
    _raises(tmp_path / "word.ply", "cannot read.*oops")
    (tmp_path / "type.ply").write_bytes(good.replace(b"property ushort", b"property half"))
    _raises(tmp_path / "type.ply", "bad PLY header line 'property half intensity'")
    (tmp_path / "fmt.ply").write_bytes(good.replace(b"binary_big_endian", b"binary_middle"))
    _raises(tmp_path / "fmt.ply", "unknown PLY format 'binary_middle'")
    (tmp_path / "noend.ply").write_bytes(good.replace(b"end_header", b"end_heady"))
    _raises(tmp_path / "noend.ply", "not a PLY file")
    (tmp_path / "novertex.ply").write_bytes(good.replace(b"element vertex", b"element point"))
    _raises(tmp_path / "novertex.ply", "no vertex element")
    (tmp_path / "listv.ply").write_bytes(good.replace(b"property char label",
                                                      b"property list uchar int label"))
    _raises(tmp_path / "listv.ply", "list properties on vertices")

    las, _, _ = _las(7, n=200)
    for ext in ("las", "laz"):
        las.write(tmp_path / f"ok.{ext}")
        data = (tmp_path / f"ok.{ext}").read_bytes()
        for cut in (1, 34 * 100, len(data) - 400):  # a byte, half the points, all the points
            p = tmp_path / f"cut{cut}.{ext}"
            p.write_bytes(data[:-cut])
            _raises(p, "truncated|cannot read")
    (tmp_path / "garbage.laz").write_bytes(b"LASF" + bytes(50))
    _raises(tmp_path / "garbage.laz", "cannot read")
    write_cloud(tmp_path / "ok.npz", PointCloud(np.ones((3, 3)), np.ones(3), np.zeros(3),
                                                 np.zeros(3)))
    data = (tmp_path / "ok.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    _raises(tmp_path / "cut.npz", "cannot read")
    np.savez(tmp_path / "noxyz.npz", points=np.ones((3, 3)))
    _raises(tmp_path / "noxyz.npz", "no 'xyz' array")
    with pytest.raises(InputError, match=r"accepted: \.ply, \.npz, \.las, \.laz"):
        write_cloud(tmp_path / "c.e57", PointCloud(np.ones((1, 3)), [1], [0], [0]))


def test_laz_without_lazrs_says_how_to_install_it(tmp_path):
    las, _, _ = _las(6, n=10)
    las.write(tmp_path / "c.laz")
    las.write(tmp_path / "c.las")
    script = f"""
import sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("lazrs", "laszip"):
            raise ModuleNotFoundError("blocked for this test: " + name)
sys.meta_path.insert(0, Block())
from apcg_core.errors import InputError
from apcg_core.io.clouds import read_cloud
assert len(read_cloud({str(tmp_path / "c.las")!r})[0]) == 10  # plain LAS needs no backend
try:
    read_cloud({str(tmp_path / "c.laz")!r})
except InputError as exc:
    print(exc)
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert "pip install lazrs" in out.stdout


# --- the add-on ---------------------------------------------------------------------------------
@pytest.fixture
def scene():
    bpy = pytest.importorskip("bpy")
    import blender_addon
    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender_addon.register()
    yield bpy.context.scene
    blender_addon.unregister()


def _attr(me, name):
    a = me.attributes[name]
    assert a.domain == "POINT"
    out = np.zeros(len(me.vertices) * (4 if a.data_type == "FLOAT_COLOR" else 1),
                   np.int32 if a.data_type == "INT" else np.float32)
    a.data.foreach_get("color_srgb" if a.data_type == "FLOAT_COLOR" else "value", out)
    return a.data_type, out


def test_import_cloud_keeps_every_attribute(scene, tmp_path):
    import bpy

    from blender_addon import api
    from blender_addon.clouds import cloud_info
    las, xyz, want = _las(7, n=120, seed=9)
    path = tmp_path / "survey.laz"
    las.write(path)
    lidar = api.add_lidar()
    assert bpy.ops.apcg.import_cloud(filepath=str(path)) == {"FINISHED"}
    obj = bpy.context.active_object
    assert obj.parent == lidar and obj.name == "survey"
    me = obj.data
    assert len(me.vertices) == 120
    names = cloud_info(obj)["attributes"]
    assert set(want) | {"Col"} <= set(names) and all(n in me.attributes for n in names)
    for k in ("intensity", "classification", "return_number", "deviation", "flags", "red"):
        kind, got = _attr(me, k)
        assert kind == "INT" and np.array_equal(got, want[k].astype(np.int64)), k
    for k in ("amplitude", "normal_1", "echo_width", "height", "gps_time"):
        kind, got = _attr(me, k)
        assert kind == "FLOAT" and np.array_equal(got, want[k].astype(np.float32)), k
    kind, got = _attr(me, "segment")  # beyond 32-bit integers: Blender keeps it as a float
    assert kind == "FLOAT" and np.array_equal(got, want["segment"].astype(np.float32))
    kind, col = _attr(me, "Col")
    rgb = np.stack([want[c] for c in ("red", "green", "blue")], 1) / 65535.0
    assert kind == "FLOAT_COLOR" and np.abs(col.reshape(-1, 4)[:, :3] - rgb).max() < 5e-4
    # the geometry is the file's
    cloud, _ = api.cloud_from_object(obj)
    assert len(cloud) == 120


def test_import_cloud_ply_names_and_8bit_colours(scene, tmp_path):
    from blender_addon import api
    rec = _vertices(4)
    props = [(n if n not in ("label", "scalar_Deviation") else
              {"label": "range", "scalar_Deviation": ".hidden/dev"}[n], t, ply)
             for n, t, ply in PROPS]
    p = tmp_path / "scan.ply"
    p.write_bytes(_header("binary_little_endian", props=props) + rec.tobytes())
    obj = api.import_cloud(p)
    me = obj.data
    # "range" is the add-on's own attribute: the file's gets a suffix; "." would hide it
    assert _attr(me, "range_1")[0] == "INT"
    assert np.array_equal(_attr(me, "range_1")[1], rec["label"])
    assert np.array_equal(_attr(me, "hidden_dev")[1], rec["scalar_Deviation"])
    assert np.array_equal(_attr(me, "nz")[1], rec["nz"])
    rgb = np.stack([rec[c] for c in ("red", "green", "blue")], 1) / 255.0
    assert np.abs(_attr(me, "Col")[1].reshape(-1, 4)[:, :3] - rgb).max() < 5e-4
    # the add-on's own attributes and export are untouched by the extra ones
    cloud, _ = api.cloud_from_object(obj)
    assert np.abs(cloud.xyz - np.stack([rec["x"], rec["y"], rec["z"]], 1)).max() < 1e-3
    back, _ = read_cloud(api.export_cloud(obj, tmp_path / "back.ply"))
    assert np.abs(back.xyz - cloud.xyz).max() < 1e-9
