"""A training run records what of its dataset defines its network (the types code by code, the
lidar, the condition space, the range quantisation, the sensor) when it starts, and every later
use of the run with a dataset (`apcg train --resume`, `apcg export --data`) refuses a dataset
that differs, in one line naming the run, the dataset and what differs; a run recorded before
that record is compared on its types, as it always was. A photon (--sensor) dataset's sensor is
recorded with a run and written into the exported model.json ("sensor"), and `apcg evaluate`
warns of it and says it in its report. A damaged checkpoint's message offers the run's kept
copies only where there are some. Real torch, real embree, datasets built by `apcg dataset
build` from tiny configs."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from apcg_core.io.dataset import read_header
from tests.cli_run import one_error, run
from training.trainer import Trainer, config_from

APCG = str(Path(sys.executable).parent / "apcg")

# 2 types x 16 samples on a 64 x 16 window (tests/data/dataset_tiny_window.toml's lidar)
CONFIG = """seed = 5
backend = "embree"
shard_size = 20
test_fraction = 0.25
sampling = "random"
samples_per_type = 16
types = ["A320neo", "Mavic 3"]

[lidar]
r_alpha_deg = {ra}
r_beta_deg = {rb}
r_r_m = 0.15
width = {w}
height = {h}
"""
LIDAR = {"ra": 0.016, "rb": 0.0304, "w": 64, "h": 16}
OTHER_LIDAR = {"ra": 0.032, "rb": 0.0608, "w": 32, "h": 8}  # the same field of view, coarser
RANGES = "\n[ranges]\naircraft_range_m = [4000, 9000]\ndrone_range_m = [150, 400]\n"
SENSOR = "1550nm-day"


def build(base: Path, name: str, lidar=LIDAR, extra: str = "", *options) -> Path:
    """A dataset built by `apcg dataset build` from a config file written here."""
    config = base / f"{name}.toml"
    config.write_text(CONFIG.format(**lidar) + extra)
    out = base / name
    r = subprocess.run([APCG, "dataset", "build", "--config", str(config), "-o", str(out),
                        "--no-progress", *options], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    return out


def train(data: Path, out: Path, **over) -> Path:
    cfg = config_from("tiny", steps=2, seed=0, batch_size=4, checkpoint_every=1,
                      family="cgan", **over)
    Trainer(data, out, cfg, progress=False, preset="tiny").fit()
    return out


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The datasets (the run's, another lidar's, another condition space's, a sensor's) and
    a run on the first (keeping a copy of every checkpoint) with its exported model."""
    base = tmp_path_factory.mktemp("stamp")
    w = {"data": build(base, "data"), "lidar": build(base, "lidar", OTHER_LIDAR),
         "ranges": build(base, "ranges", LIDAR, RANGES),
         "sensor": build(base, "sensor", LIDAR, "", "--sensor", SENSOR)}
    w["run"] = train(w["data"], base / "run", keep_every=1)
    r = subprocess.run([APCG, "export", "--run", str(w["run"]), "-o", str(base / "model")],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    w["model"] = base / "model"
    return w


# dataset -> (what differs, the dataset's value, the run's value) as the refusal says them
DIFFERS = {"lidar": ("lidar", "height 8, r_alpha_deg 0.032", "height 16, r_alpha_deg 0.016"),
           "ranges": ("condition_space", "aircraft_range_m [4000.0, 9000.0]",
                      "aircraft_range_m [3000.0, 18000.0]"),
           "sensor": ("sensor", SENSOR, "none (ideal")}


def test_a_run_records_what_of_its_dataset_defines_its_network(world):
    rec = json.loads((world["run"] / "train_config.json").read_text())
    head = read_header(world["data"])
    assert rec["dataset_defines"] == {
        "types": ["A320neo", "Mavic 3"], "lidar": head["lidar"],
        "condition_space": head["condition_space"], "quantize": True, "sensor": None}
    assert rec["dataset_types"] == ["A320neo", "Mavic 3"]  # as before, for older readers


@pytest.mark.parametrize("other", sorted(DIFFERS))
def test_export_refuses_a_dataset_the_run_did_not_learn(world, other, tmp_path, capsys):
    key, theirs, ours = DIFFERS[other]
    rc, _, err = run(["export", "--run", world["run"], "-o", tmp_path / "m", "--data",
                      world[other]], capsys)
    line = one_error(rc, err, "export", str(world["run"]), str(world[other]),
                     "not the dataset the run", f"its {key} ", theirs, "(the run's: ")
    assert ours in line.split("(the run's: ")[1]
    assert "types" not in line.split("says another):")[1]  # only what differs is named
    assert not (tmp_path / "m").exists()
    # the run's own dataset, wherever it lies now, is taken
    moved = tmp_path / "moved"
    shutil.copytree(world["data"], moved)
    rc, _, err = run(["export", "--run", world["run"], "-o", tmp_path / "m2", "--data", moved],
                     capsys)
    assert rc == 0, err
    meta = json.loads((tmp_path / "m2" / "model.json").read_text())
    assert meta["lidar"] == read_header(world["data"])["lidar"] and "sensor" not in meta


@pytest.mark.parametrize("other", sorted(DIFFERS))
def test_resume_on_a_dataset_rebuilt_otherwise_names_the_dataset(world, other, tmp_path,
                                                                 capsys):
    """The dataset at the run's path rebuilt at another lidar (or condition space, or with a
    sensor): the resume says the dataset differs, not that the preset (the network) does."""
    key, theirs, ours = DIFFERS[other]
    runs = tmp_path / "run"
    shutil.copytree(world["run"], runs)
    data = tmp_path / "data"
    shutil.copytree(world[other], data)  # the run's dataset, rebuilt in place
    rec = json.loads((runs / "train_config.json").read_text())
    rec["data"] = str(data.resolve())
    (runs / "train_config.json").write_text(json.dumps(rec))
    before = (runs / "checkpoint.pt").read_bytes()
    rc, _, err = run(["train", "--data", data, "-o", runs, "--resume", "--steps", "3",
                      "--no-progress"], capsys)
    line = one_error(rc, err, "--resume", str(runs), str(data), "not the dataset the run",
                     f"its {key} ", theirs, "(the run's: ")
    assert ours in line.split("(the run's: ")[1]
    assert "preset" not in line and "network" not in line
    assert (runs / "checkpoint.pt").read_bytes() == before


def test_a_run_recorded_before_the_record_is_compared_on_its_types(world, tmp_path, capsys):
    old = tmp_path / "old"
    shutil.copytree(world["run"], old)
    rec = json.loads((old / "train_config.json").read_text())
    del rec["dataset_defines"]
    (old / "train_config.json").write_text(json.dumps(rec))
    rc, _, err = run(["export", "--run", old, "-o", tmp_path / "m", "--data", world["ranges"]],
                     capsys)
    assert rc == 0, err  # its types are the run's: what it records agrees
    rev = tmp_path / "rev"
    shutil.copytree(world["data"], rev)
    head = json.loads((rev / "dataset.json").read_text())
    names = [t["name"] for t in head["types"]]
    for t, name in zip(head["types"], reversed(names), strict=True):
        t["name"] = name
    (rev / "dataset.json").write_text(json.dumps(head))
    rc, _, err = run(["export", "--run", old, "-o", tmp_path / "m2", "--data", rev], capsys)
    one_error(rc, err, "not the dataset the run", "its types ['Mavic 3', 'A320neo']")


def test_a_photon_run_records_its_sensor_and_its_model_says_it(world, tmp_path, capsys):
    head = read_header(world["sensor"])
    assert head["sensor"]["name"] == SENSOR
    runs = train(world["sensor"], tmp_path / "run")
    rec = json.loads((runs / "train_config.json").read_text())
    assert rec["dataset_defines"]["sensor"] == head["sensor"]
    rc, _, err = run(["export", "--run", runs, "-o", tmp_path / "m"], capsys)
    assert rc == 0, err
    assert json.loads((tmp_path / "m" / "model.json").read_text())["sensor"] == head["sensor"]
    # and a run of standard clouds is not exported with that sensor's dataset (above) nor
    # this one with the standard dataset
    rc, _, err = run(["export", "--run", runs, "-o", tmp_path / "m2", "--data",
                      world["data"]], capsys)
    one_error(rc, err, "its sensor none (ideal", f"the run's: {SENSOR} (photon clouds)")


def test_evaluate_warns_of_a_photon_dataset_and_reports_its_sensor(world, tmp_path, capsys):
    head = read_header(world["sensor"])
    rc, _, err = run(["evaluate", "--model", world["model"], "--data", world["sensor"], "-o",
                      tmp_path / "ev", "--pairs", "0", "--no-faithfulness"], capsys)
    assert rc == 0, err
    warned = [ln for ln in err.splitlines() if "warning" in ln and "sensor" in ln]
    assert len(warned) == 1 and SENSOR in warned[0] and str(world["sensor"]) in warned[0], err
    metrics = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert metrics["dataset_sensor"] == head["sensor"] and metrics["model_sensor"] is None
    assert f"photon clouds of the sensor '{SENSOR}'" in (tmp_path / "ev" / "report.md").read_text()
    # the standard dataset: no such warning, and the report says standard clouds
    rc, _, err = run(["evaluate", "--model", world["model"], "--data", world["data"], "-o",
                      tmp_path / "ev2", "--pairs", "0", "--no-faithfulness"], capsys)
    assert rc == 0, err
    assert not [ln for ln in err.splitlines() if "warning" in ln and "sensor" in ln], err
    assert json.loads((tmp_path / "ev2" / "metrics.json").read_text())["dataset_sensor"] is None
    assert "standard (ideal) clouds" in (tmp_path / "ev2" / "report.md").read_text()


def _truncated(run_dir: Path, out: Path, keep: bool) -> Path:
    shutil.copytree(run_dir, out)
    if not keep:
        shutil.rmtree(out / "checkpoints")
    ck = out / "checkpoint.pt"
    ck.write_bytes(ck.read_bytes()[:2000])
    return out


def test_a_damaged_checkpoint_offers_kept_copies_only_where_there_are_some(world, tmp_path,
                                                                          capsys):
    bare = _truncated(world["run"], tmp_path / "bare", keep=False)
    for argv in (["export", "--run", bare, "-o", tmp_path / "m"],
                 ["train", "--data", world["data"], "-o", bare, "--resume", "--no-progress"]):
        rc, _, err = run(argv, capsys)
        line = one_error(rc, err, "not a readable checkpoint", "kept no other copy",
                         "does not exist", "train the run again")
        assert "a kept copy in" not in line and "--keep-every) can replace" not in line
    (bare / "checkpoints").mkdir()  # there, but empty
    rc, _, err = run(["export", "--run", bare, "-o", tmp_path / "m"], capsys)
    one_error(rc, err, "kept no other copy", "holds none")
    kept = _truncated(world["run"], tmp_path / "kept", keep=True)
    rc, _, err = run(["export", "--run", kept, "-o", tmp_path / "m"], capsys)
    one_error(rc, err, "not a readable checkpoint", "a kept copy in", "can replace it",
              "step-000002.pt")


def test_a_network_the_datasets_lidar_cannot_shape_is_refused_in_one_line(world, tmp_path,
                                                                           capsys):
    """The cGAN's image must be a multiple of 16 a side: a 32 x 8 window is refused naming
    the dataset and its window, not with a traceback, and no run is started."""
    rc, _, err = run(["train", "--data", world["lidar"], "-o", tmp_path / "r", "--family",
                      "cgan", "--preset", "tiny", "--steps", "1", "--batch-size", "4",
                      "--no-progress"], capsys)
    one_error(rc, err, "cgan family cannot train on the dataset", str(world["lidar"]),
              "32 x 8")
    assert not (tmp_path / "r" / "train_config.json").exists()


def _scoring_commands():
    """(command path, handler) of every command with a model option and --data: each scores
    a model against a dataset (found by walking the installed parser, so a new one is
    found too)."""
    import argparse

    from apcg_core.cli import build_parser
    out = []

    def walk(parser, path):
        dests = {a.dest for a in parser._actions}
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sub in a.choices.items():
                    walk(sub, path + [name])
        if "data" in dests and dests & {"model", "models"} and parser.get_default("func"):
            out.append((" ".join(path), parser.get_default("func")))
    walk(build_parser(), [])
    return out


def test_every_command_scoring_a_model_on_a_dataset_checks_the_two_agree():
    """evaluate and compare warned of another lidar and of photon clouds; choose-tau, figure
    19 and fd-depth score did not (probe p3, stop 55): one check, warn_other_data, on every
    such path."""
    import inspect
    found = _scoring_commands()
    names = {path for path, _ in found}
    assert {"evaluate", "compare", "choose-tau", "figure", "fd-depth score"} <= names, names
    # teach's --data is where it builds its new type's own dataset, not one it scores on
    missing = [path for path, func in found if path != "teach"
               and "warn_other_data(" not in inspect.getsource(func)]
    assert not missing, missing


@pytest.mark.parametrize("argv", [["choose-tau", "--pairs", "4"],
                                  ["figure", "19", "--pairs", "4"]])
def test_scoring_on_a_photon_dataset_warns_once(world, tmp_path, capsys, argv):
    out = ["-o", tmp_path / "out.png"] if argv[0] == "figure" else []
    rc, _, err = run([*argv, "--model", world["model"], "--data", world["sensor"], *out],
                     capsys)
    warned = [ln for ln in err.splitlines() if "warning" in ln and SENSOR in ln]
    # (the 2-step model draws little: choose-tau may then refuse every threshold, after it)
    assert rc in (0, 2) and "Traceback" not in err and len(warned) == 1, err
