"""What training and export take from disk is checked before it is trusted: a model directory is
never trained over, a run is exported only with the dataset it learnt (its types code by code,
wherever the dataset now lies), a damaged dataset header is named, a model the loader would
refuse is never published, and a checkpoint of another family is not resumed. Real torch and
real commands at the tiny preset."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from apcg_core.errors import InputError
from apcg_core.io.dataset import read_header
from training.trainer import Trainer, config_from

APCG = str(Path(sys.executable).parent / "apcg")


def apcg(*argv, cwd=None):
    return subprocess.run([APCG, *map(str, argv)], capture_output=True, text=True, timeout=600,
                          cwd=cwd)


def one_error(r, *words):
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "error:" in lines[0], r.stderr
    for w in words:
        assert w in lines[0], (w, lines[0])


def digest(d: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.iterdir())
            if p.is_file()}


@pytest.fixture(scope="module")
def run_and_model(tiny_training_data, tmp_path_factory):
    base = tmp_path_factory.mktemp("runs")
    run = base / "run"
    Trainer(tiny_training_data, run, config_from("tiny", steps=2, seed=0, checkpoint_every=1),
            progress=False).fit()
    r = apcg("export", "--run", run, "-o", base / "model")
    assert r.returncode == 0, r.stderr
    return run, base / "model"


def test_training_into_a_model_directory_is_refused_and_leaves_it_whole(
        tiny_training_data, run_and_model, tmp_path):
    _, model = run_and_model
    copy = tmp_path / "model"
    shutil.copytree(model, copy)
    before = digest(copy)
    r = apcg("train", "--data", tiny_training_data, "-o", copy, "--preset", "tiny", "--steps",
             "1", "--no-progress")
    one_error(r, "is a model directory", "model.json")
    assert digest(copy) == before and sorted(p.name for p in copy.iterdir()) == sorted(before)


def test_a_run_records_its_datasets_absolute_path_and_types(tiny_training_data, run_and_model):
    run, _ = run_and_model
    rec = json.loads((run / "train_config.json").read_text())
    assert Path(rec["data"]).is_absolute() and Path(rec["data"]) == tiny_training_data.resolve()
    head = read_header(tiny_training_data)
    assert rec["dataset_types"] == [t["name"] for t in sorted(head["types"],
                                                              key=lambda t: t["code"])]


def _reversed_types_copy(data: Path, out: Path) -> Path:
    shutil.copytree(data, out)
    head = json.loads((out / "dataset.json").read_text())
    names = [t["name"] for t in head["types"]]
    for t, name in zip(head["types"], reversed(names), strict=True):
        t["name"] = name
    (out / "dataset.json").write_text(json.dumps(head))
    return out


def test_export_refuses_a_dataset_whose_types_are_not_the_runs(tiny_training_data,
                                                               run_and_model, tmp_path):
    run, _ = run_and_model
    other = _reversed_types_copy(tiny_training_data, tmp_path / "rev")
    r = apcg("export", "--run", run, "-o", tmp_path / "m", "--data", other)
    one_error(r, "export", "not the dataset the run learnt")
    assert not (tmp_path / "m").exists()
    # --data names where the right dataset is now: exported from any directory
    moved = tmp_path / "moved"
    shutil.copytree(tiny_training_data, moved)
    r = apcg("export", "--run", run.resolve(), "-o", tmp_path / "m2", "--data", moved,
             cwd=tmp_path.anchor)
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "m2" / "model.json").read_text())["types"] == json.loads(
        (run_and_model[1] / "model.json").read_text())["types"]


def test_resume_refuses_a_dataset_whose_types_are_not_the_runs(tiny_training_data,
                                                               run_and_model, tmp_path):
    run, _ = run_and_model
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    other = _reversed_types_copy(tiny_training_data, tmp_path / "rev")
    rec = json.loads((copy / "train_config.json").read_text())
    rec["data"] = str(other)  # as if the dataset had been rebuilt in place
    (copy / "train_config.json").write_text(json.dumps(rec))
    cfg = config_from("tiny", steps=3, seed=0, checkpoint_every=1)
    with pytest.raises(InputError, match="not the dataset the run learnt"):
        Trainer(other, copy, cfg, resume=True, progress=False)


def test_export_never_publishes_a_model_the_loader_refuses(run_and_model, tmp_path):
    run, _ = run_and_model
    r = apcg("export", "--run", run, "-o", tmp_path / "m", "--tau", "5")
    one_error(r, "cannot open", "tau = 5.0")
    assert not (tmp_path / "m").exists()
    assert not list(tmp_path.glob(".*staging*"))


def test_a_checkpoint_of_another_family_is_not_resumed(tiny_training_data, run_and_model,
                                                       tmp_path):
    run, _ = run_and_model
    plus = tmp_path / "plus"
    Trainer(tiny_training_data, plus, config_from("tiny", steps=1, seed=0, checkpoint_every=1,
                                                  family="apcg-plus"), progress=False).fit()
    shutil.copy(run / "checkpoint.pt", plus / "checkpoint.pt")  # the cGAN run's
    r = apcg("train", "--data", tiny_training_data, "-o", plus, "--resume", "--steps", "2",
             "--no-progress")
    assert r.returncode == 2 and "family" in r.stderr and "Traceback" not in r.stderr, r.stderr


MUTATIONS = {
    "lidar empty": (lambda h: h.update(lidar={}), "its lidar records"),
    "lidar a name": (lambda h: h.update(lidar="paper"), "must be a table"),
    "n_samples text": (lambda h: h.update(n_samples="abc"), "n_samples = 'abc'"),
    "shard without type_code": (lambda h: h["shards"][0].pop("type_code"), "lacks type_code"),
    "kind unknown": (lambda h: h["types"][0].update(kind="submarine"), "kind must be one of"),
    "depth length zero": (lambda h: h["types"][0].update(depth_length_m=0),
                          "depth_length_m must be"),
    "depth length text": (lambda h: h["types"][0].update(depth_length_m="x"),
                          "depth_length_m must be"),
    "format version": (lambda h: h.update(format_version=99), "format_version 99"),
    "n_types": (lambda h: h["condition_space"].update(n_types=5), "n_types 5"),
    "range inverted": (lambda h: h["condition_space"].update(aircraft_range_m=[18000, 3000]),
                       "lo < hi"),
    "condition space a list": (lambda h: h.update(condition_space=[1, 2]), "must be a table"),
    "n_train": (lambda h: h.update(n_train=h["n_samples"] + 100), "is not n_samples"),
    "shard count": (lambda h: h["shards"][0].update(n_samples=h["shards"][0]["n_samples"] - 1),
                    "its shards hold"),
    "shard outside": (lambda h: h["shards"][0].update(file="../x/shards/train-00000.npz"),
                      "a path inside the dataset"),
    "type name a number": (lambda h: h["types"][0].update(name=7), "name must be"),
    "split unknown": (lambda h: h["shards"][0].update(split="val"), "split must be one of"),
}


@pytest.mark.parametrize("name", sorted(MUTATIONS))
def test_a_damaged_dataset_header_is_named(tiny_training_data, tmp_path, name):
    mutate, words = MUTATIONS[name]
    head = json.loads((tiny_training_data / "dataset.json").read_text())
    mutate(head)
    (tmp_path / "dataset.json").write_text(json.dumps(head))
    with pytest.raises(InputError) as e:
        read_header(tmp_path)
    assert "is damaged" in str(e.value) and words in str(e.value), str(e.value)


def test_a_damaged_header_stops_train_in_one_line(tiny_training_data, tmp_path):
    copy = tmp_path / "ds"
    shutil.copytree(tiny_training_data, copy)
    head = json.loads((copy / "dataset.json").read_text())
    head["lidar"] = {}
    (copy / "dataset.json").write_text(json.dumps(head))
    r = apcg("train", "--data", copy, "-o", tmp_path / "run", "--preset", "tiny", "--steps",
             "1", "--no-progress")
    one_error(r, "is damaged", "its lidar records")
    assert read_header(tiny_training_data)["n_samples"] > 0  # the real header reads as it is


@pytest.mark.parametrize("edit,words", [
    (lambda m: m["types"].append(dict(m["types"][0], name="Extra")), "built for 98 types"),
    (lambda m: m["net"].update(n_types=5), "built for 5 types"),
    (lambda m: m.update(family="diffusion"), "is damaged"),
])
def test_a_model_whose_files_disagree_is_named_in_one_line(tmp_path, edit, words):
    from apcg_core.families import default_model_dir
    model = tmp_path / "m"
    shutil.copytree(default_model_dir(), model)
    meta = json.loads((model / "model.json").read_text())
    edit(meta)
    (model / "model.json").write_text(json.dumps(meta))
    r = apcg("generate", "--model", model, "--type", "A320neo", "--range-m", "4500",
             "--elevation-deg", "3.4", "--pitch-deg", "2", "-o", tmp_path / "g.ply")
    one_error(r, words)
    assert not (tmp_path / "g.ply").exists()


@pytest.mark.parametrize("family,flag,takers", [
    ("apcg-plus", "--bce", "cgan, point-gan, voxel-gan"),
    ("apcg-plus", "--no-conv", "cgan"),
    ("point-gan", "--no-norm", "cgan"),
    ("diffusion", ["--n-critic", "5"], "cgan, point-gan, voxel-gan"),
])
def test_a_switch_a_family_never_reads_is_refused(tiny_training_data, tmp_path, family, flag,
                                                  takers):
    flags = flag if isinstance(flag, list) else [flag]
    r = apcg("train", "--data", tiny_training_data, "-o", tmp_path / "run", "--family", family,
             "--preset", "tiny", "--steps", "1", "--no-progress", *flags)
    one_error(r, flags[0], f"the {family} family", takers)
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


@pytest.mark.parametrize("argv,name", [
    (["--epochs", "1e308"], "--epochs"), (["--epochs", "2e6"], "--epochs"),
    (["--family", "point-gan", "--n-points", "1000000000000"], "--n-points"),
    (["--family", "diffusion", "--diffusion-steps", "1000000000000"], "--diffusion-steps"),
    (["--n-critic", "1000"], "--n-critic"),
])
def test_counts_beyond_any_use_are_refused_before_training(tiny_training_data, tmp_path, argv,
                                                           name):
    r = apcg("train", "--data", tiny_training_data, "-o", tmp_path / "run", "--preset", "tiny",
             "--no-progress", *argv)
    one_error(r, name, "not accepted")
