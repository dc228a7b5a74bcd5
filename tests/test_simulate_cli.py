"""`apcg simulate` and the point cloud / depth image files it writes."""

import json
import struct
import zlib

import numpy as np
import pytest

from apcg_core.catalog.catalog import default_catalog
from apcg_core.cli import main
from apcg_core.condition import Condition
from apcg_core.depth import norm
from apcg_core.errors import InputError
from apcg_core.io import read_cloud, write_cloud
from dataset_builder.simulate import Simulator

POSE = ["--range-m", "4500", "--elevation-deg", "3.5", "--pitch-deg", "2", "--yaw-deg", "30",
        "--roll-deg", "-3"]


def _png_pixels(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    w, h, depth, colour = struct.unpack(">IIBB", data[16:26])
    idat = b""
    pos = 8
    while pos < len(data):
        n = struct.unpack(">I", data[pos:pos + 4])[0]
        kind = data[pos + 4:pos + 8]
        if kind == b"IDAT":
            idat += data[pos + 8:pos + 8 + n]
        pos += 12 + n
    raw = zlib.decompress(idat)
    rows = np.frombuffer(raw, np.uint8).reshape(h, 1 + 2 * w)[:, 1:]
    return depth, colour, rows.copy().view(">u2").reshape(h, w)


@pytest.mark.parametrize("ext", ["ply", "npz", "las"])
def test_simulate_writes_the_standard_cloud(tmp_path, capsys, ext):
    out = tmp_path / f"cloud.{ext}"
    code = main(["simulate", "--type", "A320neo", *POSE, "-o", str(out),
                 "--depth-image", str(tmp_path / "d.npy"),
                 "--normalized-image", str(tmp_path / "n.png")])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    cloud, meta = read_cloud(out)
    cat = default_catalog()
    cond = Condition.from_degrees(cat.get("A320neo").index, 4500, 3.5, 2, 30, -3)
    ref = Simulator("embree").simulate_type(cat, "A320neo", cond.as_array()[None]).cloud
    assert summary["points"] == len(ref) == len(cloud) > 300
    assert np.array_equal(cloud.cell_w, ref.cell_w) and np.array_equal(cloud.cell_h, ref.cell_h)
    assert np.array_equal(cloud.range_m, ref.range_m)
    tol = 1e-4 if ext == "las" else 0.0  # LAS stores 0.1 mm integer steps
    assert np.abs(cloud.xyz - ref.xyz).max() <= tol
    assert meta["type"] == "A320neo" and meta["condition"]["yaw_deg"] == pytest.approx(30)
    img = np.load(tmp_path / "d.npy")
    assert img.shape == (64, 256) and (img > -1).sum() == len(ref)
    depth, colour, px = _png_pixels(tmp_path / "n.png")
    assert (depth, colour) == (16, 0)
    expect = norm(img, cond.q)
    assert np.array_equal(px == 0, expect == -1)


def test_simulate_errors_name_the_problem(tmp_path, capsys):
    assert main(["simulate", "--type", "A320", *POSE, "-o", str(tmp_path / "a.ply")]) == 2
    assert "unknown aircraft type" in capsys.readouterr().err
    bad = ["--range-m", "12", "--elevation-deg", "3"]
    assert main(["simulate", "--type", "A320neo", *bad, "-o", str(tmp_path / "a.ply")]) == 2
    assert "bounding sphere" in capsys.readouterr().err
    assert main(["simulate", "--type", "A320neo", *POSE, "-o", str(tmp_path / "a.xyz")]) == 2
    err = capsys.readouterr().err
    assert "--output" in err and "unsupported format" in err and ".ply, .npz" in err
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_cloud_files_round_trip_and_reject_broken_files(tmp_path):
    cat = default_catalog()
    t = cat.get("Mavic 3")
    table = np.array([Condition.from_degrees(t.index, r, 3.4, 2, 10, 1).as_array()
                      for r in (150, 300)])
    cl = Simulator("embree").simulate_type(cat, t, table).cloud
    for ext in ("ply", "npz", "las"):
        p = write_cloud(tmp_path / f"c.{ext}", cl, {"k": 1})
        back, meta = read_cloud(p)
        assert meta == {"k": 1}
        assert np.array_equal(back.sample, cl.sample) and np.array_equal(back.cell_h, cl.cell_h)
    empty = cl.select(np.zeros(len(cl), bool))
    for ext in ("ply", "npz", "las"):
        back, _ = read_cloud(write_cloud(tmp_path / f"e.{ext}", empty))
        assert len(back) == 0
    ply = (tmp_path / "c.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(ply[: len(ply) - 10])
    with pytest.raises(InputError, match="truncated"):
        read_cloud(tmp_path / "t.ply")
    (tmp_path / "g.las").write_bytes(b"garbage")
    with pytest.raises(InputError, match="cannot read"):
        read_cloud(tmp_path / "g.las")
