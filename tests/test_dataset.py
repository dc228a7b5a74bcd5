"""The dataset builder: determinism, resume after SIGKILL, sharding, format, backends."""

import json
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from apcg_core.catalog.catalog import default_catalog
from apcg_core.depth import norm, pc2im
from apcg_core.errors import InputError
from apcg_core.io.dataset import Shard, shard_agreement
from apcg_core.lidar import LidarParams
from dataset_builder.build import build_dataset, dataset_info
from dataset_builder.plan import load_config, make_plan
from dataset_builder.simulate import Simulator

ROOT = Path(__file__).resolve().parents[1]
SMALL = str(ROOT / "tests" / "data" / "dataset_small.toml")
LIDAR = LidarParams()


def _files(d: Path) -> dict:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ref") / "ds"
    build_dataset(SMALL, out, progress=False)
    return out


def test_plan_is_table1_shaped_and_split_4_to_1():
    cat = default_catalog()
    plan = make_plan(load_config("paper-table1"), cat)
    assert plan.n_samples == 1_000_000
    assert len(plan.types) == 80
    assert sum(t.range_band == "near" for t in plan.types) == 4
    assert (plan.split == "test").sum() == 200_000
    counts = np.bincount(plan.table[:, 0].astype(int))
    assert (counts == 12_500).all()
    drone = plan.space.is_drone(plan.table[:, 0].astype(int))
    assert plan.table[drone, 1].max() <= 600 and plan.table[~drone, 1].min() >= 3000
    assert len(np.unique(plan.table[:, 4])) == 10 and len(np.unique(plan.table[:, 2])) == 5
    # every sample in exactly one shard, shards of one type and one split
    rows = np.concatenate([s.rows for s in plan.shards])
    assert np.array_equal(np.sort(rows), np.arange(plan.n_samples))
    for s in plan.shards[:50]:
        assert (plan.table[s.rows, 0] == s.type_code).all()
        assert (plan.split[s.rows] == s.split).all()
    again = make_plan(load_config("paper-table1"), cat)
    assert np.array_equal(plan.table, again.table) and np.array_equal(plan.split, again.split)


def test_shard_contents_match_the_simulator_and_pc2im(reference):
    head = json.loads((reference / "dataset.json").read_text())
    info = dataset_info(reference, verify=True)
    assert info["complete"] and info["samples_present"] == head["n_samples"] == 384
    assert head["n_test"] == round(0.2 * 96) * 4
    cat = default_catalog()
    spec = head["shards"][5]
    shard = Shard.load(reference / spec["file"])
    t = head["types"][spec["type_code"]]
    sim = Simulator("embree", quantize=False)
    res = sim.simulate_type(cat, t["catalog_index"], shard.conditions)
    img, stats = pc2im(res.cloud.xyz, shard.conditions[:, 1], shard.conditions[:, 2],
                       t["depth_length_m"], LIDAR, sample=res.cloud.sample,
                       n_samples=len(shard))
    dense = shard.depth_images(LIDAR.height, LIDAR.width)
    assert np.array_equal(dense, img.astype(np.float16))
    assert int(shard.n_clamped.sum()) == stats.n_clamped
    q = shard.conditions[:, 1] / np.where(shard.conditions[:, 1] >= 3000, 3000.0, 100.0)
    assert np.array_equal(shard.training_images(LIDAR.height, LIDAR.width, q),
                          norm(dense, q))
    # ranges stored to float32 precision about r0
    r = shard.conditions[np.repeat(np.arange(len(shard)), np.diff(shard.offsets)), 1]
    assert np.abs(shard.delta_range_m + r - res.cloud.range_m).max() < 1e-5
    # the conditions table on disk says the same
    lines = (reference / "conditions.csv").read_text().splitlines()
    assert len(lines) == 385
    row = lines[1 + int(shard.sample_id[0])].split(",")
    assert float(row[5]) == shard.conditions[0, 1] and row[1] == spec["split"]


def test_same_config_same_bytes_with_two_workers_and_job_array(reference, tmp_path):
    two = tmp_path / "two"
    build_dataset(SMALL, two, workers=2, progress=False)
    assert _files(two) == _files(reference)
    arr = tmp_path / "arr"
    for i in range(3):
        summary = build_dataset(SMALL, arr, shard_spec=f"{i}/3", progress=False)
        assert summary["complete"] == (i == 2)
    assert _files(arr) == _files(reference)


def test_resume_after_sigkill_is_byte_identical(tmp_path, hold):
    cfg = _write(tmp_path / "kill.toml", Path(SMALL).read_text().replace(
        "shard_size = 12", "shard_size = 2"))  # 192 shards
    ref = tmp_path / "uninterrupted"
    build_dataset(cfg, ref, progress=False)
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "apcg_core.cli", "dataset", "build", "--config", cfg,
           "-o", str(out), "--no-progress"]
    point = "build.shard-written"
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=hold.env(point))
    hold.wait(point, proc)  # killed with its lock held, the plan files and one shard written
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    hold.release(point)
    n_before = len(list((out / "shards").glob("*.npz")))
    assert n_before == 1, n_before
    assert not (out / "manifest.json").exists()
    with pytest.raises(InputError, match="not complete|incomplete|missing"):
        dataset_info(out, verify=True, require_complete=True)
    build_dataset(cfg, out, progress=False)
    assert _files(out) == _files(ref)


def test_corrupt_shard_and_other_config_are_clear_errors(reference, tmp_path):
    out = tmp_path / "c"
    shutil.copytree(reference, out)
    victim = sorted((out / "shards").glob("*.npz"))[3]
    victim.write_bytes(victim.read_bytes()[:200])
    with pytest.raises(InputError, match="corrupt"):
        dataset_info(out, verify=True)
    with pytest.raises(InputError, match="corrupt"):
        Shard.load(victim)
    cfg = load_config(SMALL)
    cfg["seed"] = 4
    with pytest.raises(InputError, match="different dataset"):
        build_dataset(cfg, out, progress=False)
    with pytest.raises(InputError, match="no dataset config"):
        load_config("no-such-config")
    with pytest.raises(InputError, match="unknown keys"):
        load_config(_write(tmp_path / "bad.toml", "sead = 1\n"))
    with pytest.raises(InputError, match="--shard"):
        build_dataset(SMALL, tmp_path / "y", shard_spec="3/3", progress=False)
    with pytest.raises(InputError, match="unknown aircraft type"):
        build_dataset({**cfg, "types": ["Concorde II"]}, tmp_path / "z", progress=False)


def _write(path: Path, text: str) -> str:
    path.write_text(text)
    return str(path)


def _compare_datasets(a: Path, b: Path):
    head = json.loads((a / "dataset.json").read_text())
    same = total = 0
    worst = 0.0
    for spec in head["shards"]:
        sa, sb = Shard.load(a / spec["file"]), Shard.load(b / spec["file"])
        assert np.array_equal(sa.conditions, sb.conditions)
        g = shard_agreement(sa, sb)
        same, total = same + g["cells_common"], total + g["cells_either"]
        worst = max(worst, g["max_range_diff_m"])
    return same / total, worst, total


def test_bpy_module_build_matches_embree(reference, tmp_path):
    out = tmp_path / "bpy"
    code = ("import bpy, sys\nbpy.ops.wm.read_factory_settings(use_empty=True)\n"
            "from dataset_builder.build import build_dataset\n"
            f"build_dataset({SMALL!r}, {str(out)!r}, backend='blender', progress=False)\n")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, timeout=600)
    same, worst, total = _compare_datasets(reference, out)
    assert total > 10_000
    assert same >= 0.995 and worst < 2e-3, (same, worst)


def test_blender_binary_build_matches_embree(reference, tmp_path, blender_binary):
    blender = blender_binary
    out = tmp_path / "bin"
    cmd = [blender, "-b", "--factory-startup", "--python-exit-code", "1", "-P",
           str(ROOT / "dataset_builder" / "blender_entry.py"), "--", "dataset", "build",
           "--config", SMALL, "-o", str(out), "--backend", "blender", "--no-progress"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    same, worst, total = _compare_datasets(reference, out)
    assert same >= 0.995 and worst < 2e-3, (same, worst)
    bad = subprocess.run(cmd[:8] + ["dataset", "build", "--config", "nope", "-o",
                                     str(tmp_path / "n")], capture_output=True, text=True,
                         timeout=600)
    assert bad.returncode == 2 and "no dataset config" in bad.stderr


@pytest.mark.parametrize("workers", [["--workers", "2"], ["--workers=2"], ["--workers"]])
def test_blender_binary_refuses_workers_in_one_line(tmp_path, blender_binary, workers):
    """Inside a Blender binary a build runs in one process: --workers other than 1, in either
    spelling, or with no value, is one error line and exit 2, nothing written, no traceback."""
    cmd = [blender_binary, "-b", "--factory-startup", "--python-exit-code", "1", "-P",
           str(ROOT / "dataset_builder" / "blender_entry.py"), "--", "dataset", "build",
           "--config", "demo", "-o", str(tmp_path / "out"), "--backend", "blender",
           "--no-progress", *workers]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert run.returncode == 2, run.stdout[-2000:] + run.stderr[-2000:]
    errors = [line for line in run.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and "--workers" in errors[0], run.stderr
    assert "Traceback" not in run.stderr and not (tmp_path / "out").exists()


def test_blender_pool_workers_live_across_shards_and_write_the_same_bytes(tmp_path):
    """Workers of a blender pool now build shard after shard (and type after type, closing old
    casters); the bytes are those of a fresh process per shard."""
    outs = {}
    for name, extra in (("reused", []), ("fresh", ["--tasks-per-process", "1"])):
        outs[name] = tmp_path / name
        run = subprocess.run([sys.executable, "-m", "apcg_core.cli", "dataset", "build",
                              "--config", "demo", "-o", str(outs[name]), "--backend",
                              "blender", "--workers", "2", "--no-progress", *extra],
                             capture_output=True, text=True, cwd=ROOT, timeout=600)
        assert run.returncode == 0, run.stderr[-2000:]
    a, b = _files(outs["reused"]), _files(outs["fresh"])
    assert len(a) > 10 and a == b


# --- a shard is done only when it is this build's, whole -----------------------------------

def _small(seed: int = 3) -> dict:
    cfg = load_config(SMALL)
    cfg["seed"] = seed
    return cfg


def test_shards_without_a_dataset_json_are_never_taken_in(tmp_path):
    build_dataset(_small(3), tmp_path / "a", progress=False)
    shutil.copytree(tmp_path / "a" / "shards", tmp_path / "b" / "shards")
    with pytest.raises(InputError, match=r"holds \d+ shard file\(s\) .* no dataset.json"):
        build_dataset(_small(4), tmp_path / "b", progress=False)
    assert not (tmp_path / "b" / "dataset.json").exists()


@pytest.mark.parametrize("damage", ["cut", "flip", "other seed"])
def test_a_damaged_or_foreign_shard_of_a_partial_build_is_built_again(tmp_path, capsys, damage):
    whole = tmp_path / "whole"
    build_dataset(_small(3), whole, progress=False)
    out = tmp_path / "parts"
    build_dataset(_small(3), out, shard_spec="0/2", progress=False)
    victim = sorted((out / "shards").glob("*.npz"))[0]
    data = bytearray(victim.read_bytes())
    if damage == "cut":
        data = data[:1000]
    elif damage == "flip":
        data[len(data) // 2] ^= 0x10
    else:
        other = tmp_path / "other"
        build_dataset(_small(4), other, progress=False)
        data = (other / "shards" / victim.name).read_bytes()
    victim.write_bytes(bytes(data))
    (out / "conditions.csv").write_text("edited\n")
    capsys.readouterr()
    summary = build_dataset(_small(3), out, shard_spec="0/2", progress=False)
    err = capsys.readouterr().err
    assert f"{victim} is not this build's" in err and "built again" in err
    assert "conditions.csv was not this build's" in err
    assert summary["built_shards"] == 1
    build_dataset(_small(3), out, shard_spec="1/2", progress=False)
    assert _files(out) == _files(whole)  # the bytes of one uninterrupted build
    assert dataset_info(out, verify=True)["complete"]


def test_a_damaged_shard_of_another_part_stops_the_manifest(tmp_path):
    out = tmp_path / "parts"
    build_dataset(_small(3), out, shard_spec="0/2", progress=False)
    victim = sorted((out / "shards").glob("*.npz"))[0]
    victim.write_bytes(victim.read_bytes()[:1000])
    with pytest.raises(InputError, match=r"is not this build's .*delete it and run --shard 0/2"):
        build_dataset(_small(3), out, shard_spec="1/2", progress=False)
    assert not (out / "manifest.json").exists()


@pytest.mark.parametrize("extra", [
    {"sampling": "grid", "counts": {"elevation": 1, "range_m": 3000, "yaw": 3000, "pitch": 1,
                                    "roll": 1}},
    {"sampling": "random", "samples_per_type": 6_000_000}])
def test_a_config_too_large_to_plan_is_refused_before_it_is_planned(extra):
    from dataset_builder.plan import MAX_SAMPLES
    cfg = {"seed": 1, "backend": "embree", "types": ["A320neo", "Mavic 3"], **extra}
    with pytest.raises(InputError, match=f"one config plans at most {MAX_SAMPLES:,}"):
        make_plan(cfg, default_catalog())


def test_a_grid_plan_is_the_product_in_its_fields_order():
    import itertools

    from dataset_builder.plan import GRID_FIELDS
    plan = make_plan(load_config(SMALL), default_catalog())
    v = plan.values
    rows = [(code, rr, b, p, y, g) for code, t in enumerate(plan.types)
            for b, rr, y, p, g in itertools.product(
                *(np.radians(v["elevation_deg"]) if f == "elevation" else
                  np.asarray(v["drone_range_m" if t.range_band == "near" else
                               "aircraft_range_m"]) if f == "range_m" else
                  np.radians(v[f"{f}_deg"]) for f in GRID_FIELDS))]
    assert np.allclose(plan.table, np.array(rows), rtol=1e-12, atol=0)
