"""Edges of PointCloud and the cloud / depth image files (probe findings, stop 54): what a
cloud is given is refused by name rather than reshaped, wrapped or truncated, and every file
write_cloud / CloudWriter writes reads back whole or is not written at all."""

import struct

import numpy as np
import pytest

from apcg_core.cloud import PointCloud
from apcg_core.errors import InputError
from apcg_core.io.clouds import CloudWriter, read_cloud, write_cloud
from apcg_core.io.images import png16_bytes, write_depth_image

ONE = ([[1.0, 2.0, 3.0]], [3.74], [0], [0])


def two():
    return PointCloud([[1.0, 2, 3], [4, 5, 6]], [3.7, 8.8], [1, 2], [3, 4], [0, 1])


def leftovers(tmp_path):
    return sorted(p.name for p in tmp_path.iterdir())


@pytest.mark.parametrize("meta", [{"type": "legend_header"}, {"name": "a\nend_header\nb"},
                                  {"end_header": ["end_header", "\r\nend_header \r\n"]}])
def test_a_ply_whose_meta_holds_end_header_reads_back(tmp_path, meta):
    # the header's end is a line of its own, not the first "end_header" in a comment
    write_cloud(tmp_path / "a.ply", two(), meta)
    with CloudWriter(tmp_path / "b.ply", meta) as w:
        w.write(two())
    for name in ("a.ply", "b.ply"):
        cloud, got = read_cloud(tmp_path / name)
        assert got == meta and np.array_equal(cloud.xyz, two().xyz)
        assert np.array_equal(cloud.sample, [0, 1])


def test_another_tools_ply_with_crlf_header_still_reads(tmp_path):
    p = tmp_path / "crlf.ply"
    p.write_bytes(b"ply\r\nformat ascii 1.0\r\ncomment made by end_header tool\r\n"
                  b"element vertex 1\r\nproperty float x\r\nproperty float y\r\n"
                  b"property float z\r\nend_header\r\n1 2 3\r\n")
    assert read_cloud(p)[0].xyz.tolist() == [[1, 2, 3]]


@pytest.mark.parametrize("args, kw, match", [
    (([[0, 1.0], [2, 3], [4, 5]], [1, 2, 3], [0] * 3, [0] * 3), {}, r"xyz .*shape \(n, 3\)"),
    (([1, 2, 3, 4], [1], [0], [0]), {}, r"xyz must have shape \(n, 3\).*got \(4,\)"),
    (([[0, 0, np.nan]], [1], [0], [0]), {}, "xyz must hold finite numbers"),
    (([[0, 0, np.inf]], [1], [0], [0]), {}, "xyz must hold finite numbers"),
    (([[0, 0, 1.0]], [np.nan], [0], [0]), {}, "range_m must hold finite numbers"),
    (([[0, 0, 1.0]], [[1.0]], [0], [0]), {}, r"range_m must have one value per point"),
    (([[0, 0, 1.0]], [1], [2**31], [0]), {}, "cell_w value 2147483648 .* does not fit"),
    (([[0, 0, 1.0]], [1], [1.7], [0]), {}, "cell_w value 1.7 .*whole numbers from"),
    (([[0, 0, 1.0]], [1], [np.nan], [0]), {}, "cell_w value nan"),
    (([[0, 0, 1.0]], [1], [0], [-2**31 - 1]), {}, "cell_h value -2147483649"),
    (([[0, 0, 1.0]], [1], [0], [0]), {"label": [300]}, "label value 300 .* from 0 to 255"),
    (([[0, 0, 1.0]], [1], [0], [0]), {"label": [-1]}, "label value -1"),
    (([[0, 0, 1.0]], [1], [0], [0]), {"count": [0.5]}, "count value 0.5"),
    (([[0, 0, 1.0]], [1], [0], [0]), {"sample": [2.0**70]}, "sample value"),
    ((np.array([[0, 0, 1.0]], object), [1], [0], [0]), {}, "xyz must hold numbers"),
    (([[0, 0, 1.0]], ["1"], [0], [0]), {}, "range_m must hold numbers"),
])
def test_point_cloud_refuses_what_it_would_reshape_wrap_or_truncate(args, kw, match):
    with pytest.raises(InputError, match=match):
        PointCloud(*args, **kw)


def test_point_cloud_takes_stored_types_as_they_are_and_converts_exact_values():
    xyz, r = np.ones((4, 3)), np.ones(4)
    w, h, s = np.arange(4, dtype=np.int32), np.zeros(4, np.int32), np.arange(4)
    c = PointCloud(xyz, r, w, h, s)
    assert c.xyz is xyz and c.range_m is r and c.cell_w is w and c.sample is s  # no copies
    c = PointCloud(xyz.astype(np.float32), [1, 2, 3, 4], [1.0, -2.0, 3.0, 2.0**31 - 1],
                   np.int64([0, 1, 2, -2**31]), label=[True, False, 1, 0])
    assert c.cell_w.dtype == np.int32 and c.cell_w.tolist() == [1, -2, 3, 2**31 - 1]
    assert c.label.tolist() == [1, 0, 1, 0] and c.cell_h.tolist()[-1] == -2**31
    assert len(PointCloud([], [], [], [])) == 0
    big = PointCloud([[1e308, 1e308, 0], [1e308, 0, 0]], [1, 1], [0, 0], [0, 0])  # sum: inf
    assert len(big) == 2


def test_split_refuses_points_of_no_sample_asked_for():
    c = PointCloud(np.zeros((3, 3)), [1, 2, 3], [0] * 3, [0] * 3, sample=[0, 2, 5])
    with pytest.raises(InputError, match="sample holds 5.*accepted: 0 to 2"):
        c.split(3)  # the point of sample 5 was dropped
    with pytest.raises(InputError, match="sample holds -1"):
        PointCloud(np.zeros((2, 3)), [1, 2], [0, 0], [0, 0], sample=[-1, 0]).split(1)
    with pytest.raises(InputError, match="n_samples must be an integer >= 0"):
        c.split(2.5)
    assert [len(x) for x in c.split(6)] == [1, 0, 1, 0, 0, 1]


@pytest.mark.parametrize("value, typ, match", [
    ("4294967296", "int", "'cell_w' value 4294967296 .*declared type int"),
    ("2.7", "int", "'cell_w' value 2.7"), ("300", "uchar", "value 300 .* from 0 to 255"),
    ("-1", "uchar", "value -1"), ("nan", "int", "value nan"),
    ("1e39", "float", r"value 1e\+39 .* up to 3.40282e\+38"),
])
def test_an_ascii_ply_value_its_type_cannot_hold_is_refused(tmp_path, value, typ, match):
    p = tmp_path / "c.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\n"
                 "property double y\nproperty double z\n"
                 f"property {typ} cell_w\nend_header\n1 2 3 {value}\n")
    with pytest.raises(InputError, match=f"{p}.*{match}"):
        read_cloud(p)


def test_ascii_ply_integers_that_fit_read_exactly(tmp_path):
    p = tmp_path / "c.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\n"
                 "property double y\nproperty double z\nproperty int cell_w\n"
                 "property uchar flag\nend_header\n1 2 3 2147483647 255\n1 2 3 -2147483648 0\n")
    cloud, _ = read_cloud(p)
    assert cloud.cell_w.tolist() == [2**31 - 1, -2**31]


@pytest.mark.parametrize("ext", [".ply", ".las"])
def test_a_sample_beyond_32_bits_is_refused_where_the_format_stores_32(tmp_path, ext):
    c = PointCloud(np.ones((1, 3)), [1.7], [0], [0], sample=[2**31 + 5])
    with pytest.raises(InputError, match=r"sample value 2147483653 .*NPZ stores any"):
        write_cloud(tmp_path / ("s" + ext), c)
    with pytest.raises(InputError, match="sample value 2147483653"), \
            CloudWriter(tmp_path / ("w" + ext)) as w:
        w.write(c)
    assert leftovers(tmp_path) == []
    write_cloud(tmp_path / "s.npz", c)
    assert read_cloud(tmp_path / "s.npz")[0].sample.tolist() == [2**31 + 5]


@pytest.mark.parametrize("ext", [".ply", ".npz", ".las"])
def test_a_cloud_changed_after_it_was_built_is_checked_before_writing(tmp_path, ext):
    for field, value in (("range_m", np.array([1.0])), ("cell_w", [1, 2, 3]),
                         ("xyz", np.zeros((2, 2))), ("label", np.ones(3, np.uint8))):
        c = two()
        setattr(c, field, value)
        with pytest.raises(InputError, match=f"cannot write .*{ext}: PointCloud.{field}"):
            write_cloud(tmp_path / ("m" + ext), c)
        with pytest.raises(InputError, match=f"PointCloud.{field}"), \
                CloudWriter(tmp_path / ("w" + ext)) as w:
            w.write(c)
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("ext", [".las", ".laz"])
def test_las_beyond_its_32_bit_extent_names_the_file(tmp_path, ext):
    pytest.importorskip("laspy")
    far = PointCloud([[0.0, 0, 1000], [0.0, 0, 500000]], [1000, 500000], [0, 0], [0, 0])
    try:
        with pytest.raises(InputError, match=rf"far{ext}: point 0 .*outside what LAS / LAZ "
                                             r"can hold.*write \.ply or \.npz"):
            write_cloud(tmp_path / ("far" + ext), far)
    except InputError as exc:  # no LAZ backend here
        pytest.skip(str(exc))
    near = PointCloud([[0.0, 0, 1000]], [1000], [0], [0])
    with pytest.raises(InputError, match=rf"w{ext}: point 0 at \[0.0, 0.0, 300000.0\]"), \
            CloudWriter(tmp_path / ("w" + ext)) as w:
        w.write(near)  # the offset is this block's centre
        w.write(PointCloud([[0.0, 0, 300000]], [300000], [0], [0]))
    assert leftovers(tmp_path) == []
    write_cloud(tmp_path / ("far" + ".ply"), far)  # what the message offers holds it


def test_write_cloud_refuses_what_is_not_a_cloud_or_a_meta(tmp_path):
    with pytest.raises(InputError, match="x.ply: expected a PointCloud, got ndarray"):
        write_cloud(tmp_path / "x.ply", np.zeros((3, 3)))
    for meta in ("text", ["a"], object()):
        for ext in (".ply", ".npz", ".las"):
            with pytest.raises(InputError, match=f"m{ext}: its meta must be"):
                write_cloud(tmp_path / ("m" + ext), PointCloud(*ONE), meta)
        with pytest.raises(InputError, match="w.npz: its meta must be"):
            CloudWriter(tmp_path / "w.npz", meta)
    with pytest.raises(InputError, match="its meta must hold JSON values"):
        write_cloud(tmp_path / "o.ply", PointCloud(*ONE), {"k": object()})
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("ext", [".ply", ".npz", ".las"])
def test_numpy_numbers_in_a_meta_are_written_as_the_numbers_they_hold(tmp_path, ext):
    meta = {"k": np.int64(3), "f": np.float32(0.5), "b": np.bool_(True), "a": np.arange(2)}
    write_cloud(tmp_path / ("a" + ext), PointCloud(*ONE), meta)
    with CloudWriter(tmp_path / ("b" + ext), meta) as w:
        w.write(PointCloud(*ONE))
    for name in ("a", "b"):
        assert read_cloud(tmp_path / (name + ext))[1] == {"k": 3, "f": 0.5, "b": True,
                                                          "a": [0, 1]}


@pytest.mark.parametrize("ext", [".png", ".npy"])
@pytest.mark.parametrize("img, match", [
    (np.zeros((0, 0)), r"got \(0, 0\)"), (np.zeros((0, 4)), r"H, W >= 1, got \(0, 4\)"),
    (np.zeros((3,)), r"shape \(H, W\)"), (np.array([[np.nan, 0.5]]), r"1 pixels .*column 0, nan"),
    (np.array([[0.5, -np.inf]]), "column 1, -inf"), (np.array([[0.5, 1e39]]), "float32"),
    (np.array([[0.5, None]], object), "holds numbers, got an array of object"),
])
def test_a_depth_image_neither_format_can_hold_is_refused(tmp_path, ext, img, match):
    with pytest.raises(InputError, match=f"d{ext}: .*{match}"):
        write_depth_image(tmp_path / ("d" + ext), img)
    assert leftovers(tmp_path) == []


def test_png_of_a_valid_image_keeps_its_size():
    data = png16_bytes(np.array([[-1.0, 0.0, 1.0]]))
    assert struct.unpack(">II", data[16:24]) == (3, 1)
    with pytest.raises(InputError, match="H, W >= 1"):
        png16_bytes(np.zeros((2, 0)))


def test_a_file_whose_range_would_not_be_finite_is_refused_by_name(tmp_path):
    # range_m defaults to the norm of xyz, which overflows for coordinates near 1e308
    p = tmp_path / "huge.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\n"
                 "property double y\nproperty double z\nend_header\n1e308 1e308 1e308\n")
    with pytest.raises(InputError, match=r"cannot read point cloud .*huge.ply: PointCloud."
                                         "range_m must hold finite numbers"):
        read_cloud(p)


def test_a_writer_of_other_photon_attributes_refuses_with_an_input_error(tmp_path):
    photon = PointCloud(*ONE, label=[1], count=[2])
    with pytest.raises(InputError, match="this writer takes clouds with no photon"), \
            CloudWriter(tmp_path / "w.ply") as w:
        w.write(photon)
    assert leftovers(tmp_path) == []
