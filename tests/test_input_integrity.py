"""Inputs read as what they say they are, outputs never in or over them, one line per refusal:
the guard's directory rule (apcg_core/outputs.py), the dataset's load-time checks
(apcg_core/io/dataset.py: manifest, shards against dataset.json and conditions.csv), a
config's plan checked whole before a build writes anything, a run's own checkpoint, FD-depth
of a family that draws clouds, and the option rules agreeing with the commands."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from apcg_core.cli import main

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MODEL = ROOT / "apcg_core/models/default"
CONFIG = ('seed = 3\nbackend = "embree"\nshard_size = 8\ntest_fraction = 0.5\n'
          'sampling = "grid"\ntypes = ["A320neo", "Mavic 3"]\n'
          '[counts]\nelevation = 1\nrange_m = 2\nyaw = 4\npitch = 2\nroll = 1\n')
TRAIN = ["--preset", "tiny", "--batch-size", "4", "--steps", "1", "--no-progress",
         "--threads", "1"]


def run(argv, capsys) -> tuple[int, str]:
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:
        rc = exc.code if isinstance(exc.code, int) else 2
    return rc, capsys.readouterr().err


def errors(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if ": error:" in ln]


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> dict:
    """d1 and, for a foreign shard, d2: the same plan (ids, split, shards) at other yaws."""
    from dataset_builder.build import build_dataset
    root = tmp_path_factory.mktemp("integrity")
    (root / "d1.toml").write_text(CONFIG)
    (root / "d2.toml").write_text(CONFIG + "[ranges]\nyaw_deg = [-50, 50]\n")
    for name in ("d1", "d2"):
        build_dataset(str(root / f"{name}.toml"), root / name, progress=False)
    return {"root": root, "d1": root / "d1", "d2": root / "d2"}


@pytest.fixture(scope="module")
def runs(data, tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("runs")
    for name, family in (("rc", "cgan"), ("rp", "apcg-plus")):
        assert main(["train", "--data", str(data["d1"]), "-o", str(root / name),
                     "--family", family, *TRAIN]) == 0
    return {"rc": root / "rc", "rp": root / "rp", "root": root}


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


# --- 6, 5. one rule for every directory output ---------------------------------------------

def test_an_output_directory_is_never_an_input_nor_inside_one(data, tmp_path, capsys):
    d1 = data["d1"]
    before = sorted(p.name for p in d1.rglob("*"))
    for argv in (["train", "--data", d1, "-o", d1, *TRAIN],
                 ["train", "--data", d1, "-o", d1 / "shards", *TRAIN],
                 ["evaluate", "--model", DEFAULT_MODEL, "--data", d1, "-o", d1, "--force"],
                 ["compare", "--model", DEFAULT_MODEL, "--data", d1, "-o", DEFAULT_MODEL],
                 ["fd-depth", "train", "--data", d1, "-o", d1, "--force"]):
        rc, err = run(argv, capsys)
        assert rc == 2 and len(errors(err)) == 1 and "input" in err, (argv, err)
    assert sorted(p.name for p in d1.rglob("*")) == before


def test_two_output_directories_that_are_one_are_refused_at_the_start(tmp_path, capsys):
    x = tmp_path / "x"
    rc, err = run(["teach", "--model", DEFAULT_MODEL, "--type", "A321neo", "-o", x,
                   "--data", x], capsys)
    assert rc == 2 and len(errors(err)) == 1 and "--data" in err, err
    assert not x.exists()


def test_export_refuses_the_runs_dataset_and_a_foreign_checkpoint(data, runs, tmp_path,
                                                                  capsys):
    rc, err = run(["export", "--run", runs["rc"], "-o", data["d1"], "--force"], capsys)
    assert rc == 2 and "input" in err, err
    rc, err = run(["export", "--run", runs["rc"], "-o", tmp_path / "m",
                   "--checkpoint", runs["rp"] / "checkpoint.pt"], capsys)
    assert rc == 2 and "--checkpoint" in err and len(errors(err)) == 1, err
    kept = runs["rc"] / "checkpoints" / "step-000001.pt"  # another family's, put among its own
    kept.parent.mkdir(exist_ok=True)
    shutil.copy(runs["rp"] / "checkpoint.pt", kept)
    try:
        rc, err = run(["export", "--run", runs["rc"], "-o", tmp_path / "m",
                       "--checkpoint", kept], capsys)
        assert rc == 2 and "not" in err and "own" in err, err
        assert not (tmp_path / "m").exists()  # the refusals made nothing
        shutil.copy(runs["rc"] / "checkpoint.pt", kept)  # the run's own kept copy
        rc, err = run(["export", "--run", runs["rc"], "-o", tmp_path / "m",
                       "--checkpoint", kept], capsys)
        assert rc == 0, err
    finally:
        shutil.rmtree(kept.parent)
    assert not (tmp_path / "m" / "sheets.onnx").exists()  # the cGAN run's model, not rp's


def test_resume_refuses_another_preset(data, runs, capsys):
    rc, err = run(["train", "--data", data["d1"], "-o", runs["rc"], "--resume", "--preset",
                   "paper", "--steps", "2", "--no-progress"], capsys)
    assert rc == 2 and "--preset paper" in err and "tiny" in err, err


# --- 8. one line -------------------------------------------------------------------------

def test_one_error_line_for_a_bad_option_and_an_existing_output(data, tmp_path, capsys):
    out = tmp_path / "a.npz"
    out.write_bytes(b"mine")
    rc, err = run(["simulate", "--type", "A320neo", "--range-m", "nan", "--elevation-deg", "3",
                   "-o", out], capsys)
    assert rc == 2 and len(errors(err)) == 1 and "--range-m" in err, err
    rep = tmp_path / "rep"
    rep.mkdir()
    for f in ("metrics.json", "report.md", "fig17.png"):
        (rep / f).write_bytes(b"mine")
    rc, err = run(["evaluate", "--data", data["d1"], "-o", rep], capsys)
    assert rc == 2 and len(errors(err)) == 1, err
    assert all(f in err for f in ("metrics.json", "report.md", "fig17.png")), err


# --- 3, 7. a dataset read as what it says it is ------------------------------------------

def test_a_swapped_shard_is_refused_by_name_where_it_is_read(data, tmp_path):
    from apcg_core.errors import InputError
    from training.data import DepthDataset
    DepthDataset(data["d1"], "train")  # the dataset as built: read
    within = _copy(data["d1"], tmp_path / "within")
    shards = sorted(p.name for p in (within / "shards").glob("train-*.npz"))
    shutil.copy(within / "shards" / shards[0], within / "shards" / shards[1])
    foreign = _copy(data["d1"], tmp_path / "foreign")
    shutil.copy(data["d2"] / "shards" / shards[0], foreign / "shards" / shards[0])
    for d, name in ((within, shards[1]), (foreign, shards[0])):
        with pytest.raises(InputError, match=name):
            DepthDataset(d, "train")


def test_info_and_readers_name_a_missing_shard_an_edited_header_and_a_bad_manifest(
        data, tmp_path, capsys):
    from apcg_core.errors import InputError
    from training.data import DepthDataset
    gone = _copy(data["d1"], tmp_path / "gone")
    last = sorted((gone / "shards").glob("test-*.npz"))[-1]
    last.unlink()
    rc, err = run(["dataset", "info", gone, "--verify"], capsys)
    assert rc == 2 and last.name in err, err
    with pytest.raises(InputError, match=last.stem):
        DepthDataset(gone, "test")
    edited = _copy(data["d1"], tmp_path / "edited")
    head = json.loads((edited / "dataset.json").read_text())
    head["n_samples"] -= 1
    (edited / "dataset.json").write_text(json.dumps(head))
    rc, err = run(["dataset", "info", edited, "--verify"], capsys)
    assert rc == 2 and "dataset.json" in err and "n_samples" in err, err
    head["n_samples"] += 1
    head["types"][0]["name"], head["types"][1]["name"] = (head["types"][1]["name"],
                                                          head["types"][0]["name"])
    (edited / "dataset.json").write_text(json.dumps(head))
    rc, err = run(["dataset", "info", edited, "--verify"], capsys)
    assert rc == 2 and "types" in err, err
    cut = _copy(data["d1"], tmp_path / "cut")
    text = (cut / "manifest.json").read_text()
    (cut / "manifest.json").write_text(text[: len(text) // 2])
    rc, err = run(["dataset", "info", cut], capsys)
    assert rc == 2 and "manifest.json" in err, err
    with pytest.raises(InputError, match="manifest.json"):
        DepthDataset(cut, "train")


# --- 4. a config's plan checked whole before anything is written --------------------------

@pytest.mark.parametrize("ranges,key", [
    ("pitch_deg = [-1000, 1000]", "ranges.pitch_deg"),
    ("elevation_deg = [80, 200]", "ranges.elevation_deg"),
    ("aircraft_range_m = [5, 10]", "ranges.aircraft_range_m"),
    ("aircraft_range_m = [5000, 5000]", "ranges.aircraft_range_m")])
def test_a_config_refused_by_its_plan_writes_nothing(tmp_path, capsys, ranges, key):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(CONFIG.replace("[counts]", f"[ranges]\n{ranges}\n[counts]"))
    out = tmp_path / "ds"
    rc, err = run(["dataset", "build", "--config", cfg, "-o", out, "--no-progress"], capsys)
    assert rc == 2 and not out.exists(), err
    assert err.strip().count("\n") == 0 and str(cfg) in err and key in err, err


# --- 1. FD-depth of a family that draws clouds --------------------------------------------

def test_fd_depth_scores_an_apcg_plus_model(data):
    from training.data import DepthDataset
    from training.fd_depth import DepthEncoder, fd_depth
    ds = DepthDataset(data["d1"], "test")
    enc = DepthEncoder(len(ds.types), ds.height, ds.width).eval()
    rep = fd_depth(enc, __import__("apcg_core.families", fromlist=["load_model"]).load_model(
        DEFAULT_MODEL), data["d1"], n_pairs=None)
    assert np.isfinite(rep["fd_depth"]) and rep["pairs"] >= 2


# --- 10. the option rules agree with the commands ----------------------------------------

def test_option_rules_agree_with_the_commands(capsys):
    from apcg_core.options import problems
    assert problems({"pairs": 0}) == []  # 0: every held-out pair, for every command
    assert "8" in problems({"samples": 1})[0] and "8" in problems({"samples": 0})[0]
    sheet = problems({"sheet": 512})
    assert sheet and "512" not in sheet[0].split("accepted:")[1], sheet
    assert problems({"sheet": 256}) == [] and problems({"voxel_res": 8}) == []
    assert "8" in problems({"voxel_res": 4})[0] and "8" in problems({"voxel_res": 1024})[0]
