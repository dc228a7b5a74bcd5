"""`apcg generate` of any size: block by block, in bounded memory, into any format."""

import numpy as np
import pytest

import apcg_core.generation_cli as gen
from apcg_core.cli import main
from apcg_core.generation_job import block_seed
from apcg_core.io import read_cloud

POSE = ["--type", "A320neo", "--range-m", "3000", "--elevation-deg", "3", "--pitch-deg", "2"]


def test_blocks_cover_every_cloud_once_in_order():
    class T(list):
        def __getitem__(self, s):
            return T(list.__getitem__(self, s))
    for rows, count, size in ((1, 7, 3), (5, 1, 2), (4, 3, 5), (3, 10, 4), (6, 2, 100)):
        table = T(range(rows))
        seen = []
        for part, k, offset in gen.blocks(table, count, size):
            assert len(part) * k <= size or len(part) == 1
            assert offset == len(seen)
            seen += [r for r in part for _ in range(k)]
        assert seen == [r for r in range(rows) for _ in range(count)]


def test_block_seeds_differ_and_block_0_keeps_the_seed():
    assert block_seed(7, 0) == 7
    seeds = {block_seed(s, b) for s in range(5) for b in range(1, 50)}
    assert len(seeds) == 5 * 49


@pytest.mark.parametrize("ext", ["ply", "las", "npz"])
def test_streamed_output_equals_one_block(tmp_path, monkeypatch, ext):
    assert main(["generate", *POSE, "--count", "5", "-o", str(tmp_path / f"one.{ext}")]) == 0
    monkeypatch.setattr(gen, "BLOCK_CLOUDS", 2)  # 3 blocks of at most 2 clouds
    assert main(["generate", *POSE, "--count", "5", "-o", str(tmp_path / f"many.{ext}")]) == 0
    one, meta1 = read_cloud(tmp_path / f"one.{ext}")
    many, meta2 = read_cloud(tmp_path / f"many.{ext}")
    assert len(one) > 0 and len(one) == len(many)
    assert sorted(set(many.sample.tolist())) == [0, 1, 2, 3, 4]
    # APCG+ has no noise: every block gives the same clouds, in the same order
    np.testing.assert_allclose(many.xyz, one.xyz, atol=2e-4)
    np.testing.assert_array_equal(many.sample, one.sample)
    assert meta1 == meta2 and meta2["count"] == 5
    assert not list(tmp_path.glob("*.part"))


def test_npz_streams_to_the_bytes_savez_writes(tmp_path):
    """The NPZ writer holds no clouds: each array streams to a spill file and is copied into
    the zip at the end; the members are those np.savez writes for the whole cloud at once."""
    import zipfile

    from apcg_core.cloud import PointCloud
    from apcg_core.io.clouds import CloudWriter, write_cloud
    rng = np.random.default_rng(3)
    parts = []
    for k in range(4):
        n = int(rng.integers(0, 50))
        parts.append(PointCloud(rng.normal(size=(n, 3)), rng.uniform(1, 9, n),
                                rng.integers(-9, 9, n), rng.integers(-9, 9, n),
                                np.full(n, k), label=rng.integers(0, 2, n),
                                count=rng.integers(1, 5, n)))
    meta = {"clouds": 4}
    with CloudWriter(tmp_path / "streamed.npz", meta, photon_fields=("label", "count")) as w:
        for p in parts:
            w.write(p)
        spilled = {x.name for x in tmp_path.iterdir()}
    # the first member (xyz) is written in place in the zip, the others spill beside it
    assert spilled == {"streamed.npz.part"} | {f"streamed.npz.{k}.part" for k in
                                              ("range_m", "cell_w", "cell_h", "sample", "label",
                                               "count")}
    whole = PointCloud(*(np.concatenate([getattr(p, k) for p in parts])
                         for k in ("xyz", "range_m", "cell_w", "cell_h", "sample")),
                       label=np.concatenate([p.label for p in parts]),
                       count=np.concatenate([p.count for p in parts]))
    write_cloud(tmp_path / "whole.npz", whole, meta)
    a, b = zipfile.ZipFile(tmp_path / "streamed.npz"), zipfile.ZipFile(tmp_path / "whole.npz")
    assert [i.filename for i in a.infolist()] == [i.filename for i in b.infolist()]
    for name in a.namelist():
        assert a.read(name) == b.read(name), name
    assert sorted(x.name for x in tmp_path.iterdir()) == ["streamed.npz", "whole.npz"]


def test_npz_writer_interrupted_leaves_nothing(tmp_path):
    from apcg_core.cloud import PointCloud
    from apcg_core.io.clouds import CloudWriter
    with pytest.raises(KeyboardInterrupt), CloudWriter(tmp_path / "x.npz") as w:
        w.write(PointCloud(np.zeros((3, 3)), np.ones(3), [0, 1, 2], [0, 0, 0], [0, 0, 0]))
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_npz_kernel_copy_writes_the_zip_of_the_plain_copy(tmp_path, monkeypatch):
    """Where the kernel copies the spilled arrays into the zip (os.copy_file_range), the file
    is the one the plain copy through zipfile writes, byte for byte, its CRCs right."""
    import os
    import zipfile

    from apcg_core.cloud import PointCloud
    from apcg_core.io.clouds import CloudWriter
    rng = np.random.default_rng(5)
    parts = []
    for k in range(5):
        n = int(rng.integers(0, 4000)) if k != 2 else 0  # an empty block among them
        parts.append(PointCloud(rng.normal(size=(n, 3)), rng.uniform(1, 9, n),
                                rng.integers(-9, 9, n), rng.integers(-9, 9, n),
                                np.full(n, k)))

    def write(name):
        with CloudWriter(tmp_path / name, {"clouds": 5}) as w:
            for p in parts:
                w.write(p)
        return (tmp_path / name).read_bytes()

    assert hasattr(os, "copy_file_range")  # Linux: the fast path is the one taken here
    fast = write("fast.npz")
    kernel_copy = os.copy_file_range

    def refuses_part_way(src, dst, count, offset_src=None, offset_dst=None):
        if offset_src:  # the first piece is copied, then the file system refuses
            raise OSError(95, "not supported here")
        return kernel_copy(src, dst, min(count, 1000), offset_src, offset_dst)

    monkeypatch.setattr(os, "copy_file_range", refuses_part_way)
    cut = write("cut.npz")
    monkeypatch.delattr(os, "copy_file_range")
    plain = write("plain.npz")
    assert fast == plain
    assert cut == plain  # the partial copy cut off, the member written again in full
    from apcg_core.io import clouds
    monkeypatch.setattr(clouds._DirectMember, "supported", staticmethod(lambda: False))
    write("zipfile.npz")  # every member through zipfile's own writes and CRCs
    with zipfile.ZipFile(tmp_path / "fast.npz") as z, \
            zipfile.ZipFile(tmp_path / "zipfile.npz") as y:
        assert z.testzip() is None  # every member's CRC checks
        assert [(i.filename, i.CRC, i.file_size) for i in z.infolist()] == \
            [(i.filename, i.CRC, i.file_size) for i in y.infolist()]
        assert all(z.read(n) == y.read(n) for n in z.namelist())
    got = np.load(tmp_path / "fast.npz")
    assert np.array_equal(got["xyz"], np.concatenate([p.xyz for p in parts]))
    assert np.array_equal(got["sample"], np.concatenate([p.sample for p in parts]))


@pytest.mark.parametrize("la, lb", [(0, 0), (0, 9), (9, 0), (1, 1), (128, 65536), (7, 12345),
                                    (3000, 1)])
def test_crc32_combine_is_the_crc_of_the_concatenation(la, lb):
    import os
    import zlib

    from apcg_core.io.crc import crc32_combine
    a, b = os.urandom(la), os.urandom(lb)
    assert crc32_combine(zlib.crc32(a), zlib.crc32(b), lb) == zlib.crc32(a + b)
    with pytest.raises(ValueError, match="len_b"):
        crc32_combine(0, 0, -1)


@pytest.mark.parametrize("size", [0, 1, 15, 16, 17, 255, 4096, 65537, (1 << 20) + 3])
def test_the_packages_crc32_is_zlibs_in_pieces_and_whole(size):
    """Every CRC the package writes goes through apcg_core.io.crc.crc32 (ISA-L's where the
    io extra installed it): zlib's values, from any start value, over unaligned pieces."""
    import os
    import zlib

    from apcg_core.io.crc import crc32
    data = os.urandom(size)
    assert crc32(data) == zlib.crc32(data)
    assert crc32(memoryview(data)[3:]) == zlib.crc32(data[3:])
    cut = size // 3
    assert crc32(data[cut:], crc32(data[:cut])) == zlib.crc32(data)
    assert crc32(data, 0xDEADBEEF) == zlib.crc32(data, 0xDEADBEEF)


def test_the_io_extra_gives_the_fast_crc32():
    """The set-up command installs the io extra, whose isal the package's CRC comes from (zlib's
    is the fallback without it): CI runs with the one users get."""
    from apcg_core.io.crc import crc32
    assert crc32.__module__.startswith("isal"), crc32.__module__


def test_npz_writer_spills_every_member_where_zipfile_is_another(tmp_path, monkeypatch):
    """Where this Python's zipfile keeps a member's size and CRC elsewhere, the first member is
    spilled and copied like the others: the same arrays either way."""
    from apcg_core.cloud import PointCloud
    from apcg_core.io import clouds
    rng = np.random.default_rng(2)
    parts = [PointCloud(rng.normal(size=(n, 3)), rng.uniform(1, 9, n), rng.integers(0, 9, n),
                        rng.integers(0, 9, n), np.full(n, k)) for k, n in enumerate((5, 0, 7))]
    assert clouds._DirectMember.supported()  # this Python: xyz written in place
    got = {}
    for inplace in (True, False):
        monkeypatch.setattr(clouds._DirectMember, "supported", staticmethod(lambda v=inplace: v))
        with clouds.CloudWriter(tmp_path / f"{inplace}.npz", {"n": 3}) as w:
            for p in parts:
                w.write(p)
            spilled = sorted(x.name for x in tmp_path.iterdir() if x.name.startswith(str(inplace)))
        assert (f"{inplace}.npz.xyz.part" in spilled) == (not inplace)
        with np.load(tmp_path / f"{inplace}.npz") as z:
            got[inplace] = {k: z[k] for k in ("xyz", "range_m", "cell_w", "cell_h", "sample")}
    for k, a in got[True].items():
        assert a.tobytes() == got[False][k].tobytes(), k
    assert len(got[True]["xyz"]) == 12
