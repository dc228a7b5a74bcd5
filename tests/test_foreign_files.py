"""A file of ANOTHER dataset or job that matches this one's plan (the same sample ids and
conditions) is never taken as this one's: a shard built with another lidar, backend or sensor
is refused by every reader, by name, and made again by a resumed build (each shard records
its dataset: apcg_core.io.dataset.foreign_shard); a shard written before shards recorded it is
checked by its content; a part of another `apcg generate --resumable` job is made again
(apcg_core.generation_job._part_problem)."""

import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from cli_run import run

import apcg_core.generation_cli as gen
from apcg_core.errors import InputError
from apcg_core.io.dataset import Shard, read_condition_index, read_header
from dataset_builder.build import build_dataset, dataset_info
from training.data import DepthDataset

# 2 types x 12 random samples, shards of 6: 4 train and 2 test shards, built in well under 1 s
CONFIG = {"seed": 3, "backend": "embree", "shard_size": 6, "test_fraction": 0.25,
          "sampling": "random", "samples_per_type": 12, "types": ["A320neo", "Mavic 3"]}
# the same plan (samples and conditions), another dataset: what each one's shards differ by
OTHER = {"half-cells": ({"lidar": "half-cells"}, "another lidar"),
         "points": ({"backend": "points"}, "another backend"),
         "sensor": ({"sensor": "1550nm-day"}, "another sensor")}


def _files(d: Path) -> dict:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("foreign")
    out = {"ref": root / "ref"}
    build_dataset(dict(CONFIG), out["ref"], progress=False)
    for name, (kw, _) in OTHER.items():
        out[name] = root / name
        build_dataset(dict(CONFIG), out[name], progress=False, **kw)
        # the same plan: only the stamp (or the content) tells the shards apart
        assert (out[name] / "conditions.csv").read_bytes() == \
            (out["ref"] / "conditions.csv").read_bytes()
    return out


def _test_shard(d: Path) -> str:
    return next(s["file"] for s in read_header(d)["shards"] if s["split"] == "test")


def _train_shard(d: Path) -> str:
    return next(s["file"] for s in read_header(d)["shards"] if s["split"] == "train")


def _old_style(path: Path) -> None:
    """``path`` rewritten as a shard built before shards recorded their dataset (no member
    ``dataset``; every array as it is)."""
    shard = Shard.load(path)
    shard.dataset = None
    path.write_bytes(shard.to_bytes())
    with zipfile.ZipFile(path) as z:
        assert "dataset.npy" not in z.namelist()


@pytest.mark.parametrize("other", sorted(OTHER))
def test_every_reader_refuses_a_shard_of_another_dataset_by_name(built, tmp_path, capsys,
                                                                 other):
    data = tmp_path / "ds"
    shutil.copytree(built["ref"], data)
    name = _test_shard(data)
    shutil.copyfile(built[other] / name, data / name)
    says = OTHER[other][1]
    with pytest.raises(InputError) as e:
        DepthDataset(data, "test")
    msg = str(e.value)
    assert str(data / name) in msg and "belongs to another dataset" in msg and says in msg, msg
    rc, _, err = run(["evaluate", "--data", data, "-o", tmp_path / "ev", "--no-faithfulness"],
                     capsys)
    assert rc == 2 and str(data / name) in err and says in err, err
    assert not (tmp_path / "ev").exists()
    with pytest.raises(InputError, match=name):
        dataset_info(data, verify=True)


@pytest.mark.parametrize("manifest", [False, True], ids=["interrupted", "finished"])
@pytest.mark.parametrize("other", sorted(OTHER))
def test_a_resumed_build_makes_a_shard_of_another_dataset_again(built, tmp_path, capsys,
                                                                other, manifest):
    data = tmp_path / "ds"
    shutil.copytree(built["ref"], data)
    if not manifest:
        (data / "manifest.json").unlink()  # an interrupted build
    name = _train_shard(data)
    shutil.copyfile(built[other] / name, data / name)
    capsys.readouterr()
    summary = build_dataset(dict(CONFIG), data, progress=False)
    err = capsys.readouterr().err
    assert f"{data / name} is not this build's" in err and OTHER[other][1] in err, err
    assert "built again" in err
    assert summary["built_shards"] == 1 and summary["complete"]
    assert _files(data) == _files(built["ref"])  # the bytes of one uninterrupted build
    assert dataset_info(data, verify=True)["verified"]


def test_a_shard_built_before_shards_recorded_their_dataset(built, tmp_path, capsys):
    """Read by its content: this dataset's own arrays are read; pixels past the header's
    W x H, or photon arrays in an ideal dataset, are refused by name. A resumed build makes
    it again (what it writes records its dataset)."""
    data = tmp_path / "ds"
    shutil.copytree(built["ref"], data)
    name = _test_shard(data)
    _old_style(data / name)
    mine = DepthDataset(data, "test")  # an old dataset's own shard: read as before
    assert len(mine.sample_id) == 6
    head = read_header(data)
    cells = head["lidar"]["width"] * head["lidar"]["height"]
    for other, says in [("half-cells", "another lidar"), ("sensor", "built with a sensor")]:
        shutil.copyfile(built[other] / name, data / name)
        _old_style(data / name)
        if other == "half-cells":  # pixels this dataset's image does not have
            assert Shard.load(data / name).pixel.max() >= cells
        with pytest.raises(InputError) as e:
            DepthDataset(data, "test")
        msg = str(e.value)
        assert str(data / name) in msg and "belongs to another dataset" in msg \
            and says in msg, msg
    # the reader's check straight, as every reader calls it
    from apcg_core.io.dataset import load_shard
    entry = next(s for s in head["shards"] if s["file"] == name)
    with pytest.raises(InputError, match="photon arrays"):
        load_shard(data, entry, read_condition_index(data, head), head)
    (data / "manifest.json").unlink()
    capsys.readouterr()
    assert build_dataset(dict(CONFIG), data, progress=False)["built_shards"] == 1
    assert f"{data / name} is not this build's" in capsys.readouterr().err
    assert _files(data) == _files(built["ref"])


def test_a_part_of_another_generate_job_is_made_again(tmp_path, monkeypatch, capsys):
    """Two resumable jobs stopped before their output (parts of 2 clouds: 3 parts each);
    another job's part, another part of this job and a part that records no job, put in
    this job's parts directory: each is made again, and the output is the uninterrupted
    one's, byte for byte."""
    import apcg_core.generation_job as job
    from apcg_core.cli import main
    monkeypatch.setattr(gen, "BLOCK_CLOUDS", 2)
    pose = ["--type", "A320neo", "--elevation-deg", "3", "--pitch-deg", "2", "--count", "5"]
    mine = ["generate", *pose, "--range-m", "3000"]
    other = ["generate", *pose, "--range-m", "3200"]
    assert main([*mine, "-o", str(tmp_path / "d.npz")]) == 0
    whole = job._write_output

    def stop(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(job, "_write_output", stop)
    assert main([*mine, "--resumable", "-o", str(tmp_path / "a.npz")]) == 130
    assert main([*other, "--resumable", "-o", str(tmp_path / "b.npz")]) == 130
    monkeypatch.setattr(job, "_write_output", whole)
    a, b = tmp_path / "a.npz.parts", tmp_path / "b.npz.parts"
    shutil.copyfile(b / "part-000000.npz", a / "part-000000.npz")  # another job's
    shutil.copyfile(a / "part-000002.npz", a / "part-000001.npz")  # another part of this job
    with np.load(a / "part-000002.npz") as z:  # one that records no job (an older apcg's)
        arrays = {k: z[k] for k in z.files if k != "job"}
    np.savez(a / "part-000002.npz", **arrays)
    capsys.readouterr()
    assert main([*mine, "--resumable", "-o", str(tmp_path / "a.npz")]) == 0
    err = capsys.readouterr().err
    za, zd = zipfile.ZipFile(tmp_path / "a.npz"), zipfile.ZipFile(tmp_path / "d.npz")
    assert za.namelist() == zd.namelist()
    assert [n for n in za.namelist() if za.read(n) != zd.read(n)] == []
    for i, why in [(0, "another job"), (1, "part 2 of this job"), (2, "records no job")]:
        line = f"{a / f'part-00000{i}.npz'} is not this job's"
        assert line in err and why in err, err
    assert not a.exists()


def test_a_foreign_part_is_refused_at_assembly(tmp_path):
    """The assembly's own check (a part that appears after the start of the run, say):
    named, nothing written under the output's name."""
    import apcg_core.generation_job as job
    from apcg_core.cloud import PointCloud
    parts = tmp_path / "o.npz.parts"
    parts.mkdir()
    cloud = PointCloud(np.zeros((1, 3), np.float32), np.ones(1, np.float32),
                       np.zeros(1, np.int16), np.zeros(1, np.int16), np.zeros(1, np.int64))
    stamp = job.part_stamp("0" * 64, 0, 1, 1)
    job._write_part(parts / "part-000000.npz", [(cloud, 1)], (), ".x.part",
                    job.part_stamp("1" * 64, 0, 1, 1))
    with pytest.raises(InputError, match="part-000000.npz is not this job's .*another job"):
        job._write_output(tmp_path / "o.npz", {}, (), parts, 1, [stamp])
    assert not (tmp_path / "o.npz").exists()
