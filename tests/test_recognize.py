"""`apcg benchmark recognize` (training/recognize.py): real embree clouds, real torch, tiny sizes.

Each test can fail: the controls (shuffled labels, a source of pure noise, a training set of one
type) must score chance or below while the same run's classifier trained on exact clouds with
the true labels scores well above it."""

import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from training import recognize

_SCRIPT = Path(sys.executable).parent / "apcg"
DEFAULT_MODEL = Path(recognize.__file__).resolve().parents[1] / "apcg_core" / "models" / "default"
APCG = str(_SCRIPT) if _SCRIPT.exists() else shutil.which("apcg")

# three types told apart by shape and size at every range of their band
TYPES = ["777-300ER", "F-16C Fighting Falcon", "UH-60 Black Hawk"]
# a narrow network on few points: the true labels reach 80-90% in seconds
SMALL = dict(types=TYPES, train_per_type=30, test_per_type=20, epochs=24, n_boot=200, width=16,
             n_points=96, networks=1)


def _cli(*args):
    return subprocess.run([APCG, "benchmark", "recognize", *args], capture_output=True,
                          text=True, timeout=300)


def _without_cost(rep):
    """The report without its wall-clock values (and the command line)."""
    if isinstance(rep, dict):
        return {k: _without_cost(v) for k, v in rep.items() if k not in ("cost", "command")}
    return [_without_cost(v) for v in rep] if isinstance(rep, list) else rep


def test_the_command_runs_end_to_end_and_is_deterministic(tmp_path):
    from apcg_core.families import default_model_dir
    from apcg_core.lidar import load_lidar
    model = str(default_model_dir())
    args = ["--source", "exact", "--source", model, "--types", "777-300ER,Mavic 3",
            "--train-per-type", "6", "--test-per-type", "5", "--epochs", "2", "--bootstrap",
            "50", "--seed", "3", "--lidar", "double-cells", "--networks", "2"]
    a = _cli(*args, "-o", str(tmp_path / "a"))
    assert a.returncode == 0, a.stderr
    for name in recognize.REPORT_FILES:
        assert (tmp_path / "a" / name).stat().st_size > 0
    rep = json.loads((tmp_path / "a" / "recognize.json").read_text())
    assert rep["sizes"]["train_clouds"] == 12 and rep["sizes"]["test_clouds"] == 10
    assert rep["types"] == ["777-300ER", "Mavic 3"] and rep["chance"] == 0.5
    # two networks per training set: their confusions summed, their top-1s averaged
    assert sum(map(sum, rep["trained_on_exact"]["confusion"])) == 20
    assert rep["sizes"]["networks"] == 2 and len(rep["trained_on_exact"]["networks"]) == 2
    assert rep["trained_on_exact"]["top1"] == pytest.approx(
        np.mean(rep["trained_on_exact"]["networks"]), abs=1e-6)
    exact, generated = rep["sources"]
    # exact against exact: the same clouds, labels and seed make the same classifier
    assert exact["tstr"]["overall"]["ratio"] in (None, 1.0)
    assert exact["trained_on_source"] == rep["trained_on_exact"]
    assert generated["source"]["kind"] == "model" and generated["source"]["family"]
    assert generated["mean_points"] > 0
    assert set(generated["tstr"]["bands"]) == set(rep["test"]["per_band"])
    assert "| **all** |" in (tmp_path / "a" / "report.md").read_text()
    # the same command in another process: the same scores to the last digit
    assert rep["test"]["lidar"] == load_lidar("double-cells").to_dict()
    again = recognize.run(["exact", model], ["777-300ER", "Mavic 3"], 6, 5, 2, seed=3,
                          n_boot=50, lidar=load_lidar("double-cells"), networks=2)
    assert _without_cost(json.loads(json.dumps(again))) == _without_cost(rep)
    # the command it records can be pasted back: "Mavic 3" stays one argument
    assert shlex.split(rep["command"]) == ["apcg", "benchmark", "recognize", *args, "-o",
                                           str(tmp_path / "a")]


def test_two_models_in_directories_of_one_name_are_told_apart_in_the_report(tmp_path):
    srcs = [{"source": {"source": str(tmp_path / d / "default"), "kind": "model"}}
            for d in ("one", "two")] + [{"source": {"source": "exact", "kind": "simulator"}}]
    assert recognize._labels(srcs) == [str(tmp_path / "one" / "default"),
                                      str(tmp_path / "two" / "default"), "exact"]
    assert recognize._labels(srcs[1:]) == ["default", "exact"]


def test_photon_clouds_of_every_kind_of_source():
    from apcg_core.families import default_model_dir
    from apcg_core.sensor import load_sensor
    rep = recognize.run(["points", "embree-2x2", str(default_model_dir())],
                        ["A320neo", "Mavic 3"], 3, 2, 1, seed=5,
                        sensor=load_sensor("1550nm-day"), n_boot=0, width=8, n_points=32)
    assert rep["test"]["sensor"]["name"] == "1550nm-day" and rep["test"]["supersample"] == 4
    for src in rep["sources"]:
        assert src["mean_points"] > 0 and src["source"]["sensor"]["name"] == "1550nm-day"


@pytest.mark.parametrize("args,needle", [
    (["--source", "nowhere"], "--source 'nowhere' is neither a model directory nor one of"),
    (["--types", "A320neo"], "at least two types"),
    (["--types", "A320neo,Concorde"], "Concorde"),
    (["--source", "points", "--sensor", "nonsense-preset"], "nonsense-preset"),
    (["--source", ""], "--source '': an empty name"),
    (["--source", "exact", "--source", "exact"], "'exact' is given twice"),
    (["--source", str(DEFAULT_MODEL), "--source", f"{DEFAULT_MODEL}/../default/"],
     "is given twice"),
    (["--train-per-type", "100000000"], "--train-per-type 100000000 not accepted"),
    (["--test-per-type", "0"], "--test-per-type 0 not accepted"),
])
def test_bad_input_is_one_clear_line(tmp_path, args, needle):
    sizes = {"--train-per-type": "2", "--test-per-type": "2", "--epochs": "1"}
    out = _cli(*args, *[w for k, v in sizes.items() if k not in args for w in (k, v)],
               "-o", str(tmp_path / "r"))
    assert out.returncode == 2, out.stderr
    assert needle in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "r" / "recognize.json").exists()


def test_a_broken_model_source_is_refused_before_any_classifier_trains(tmp_path):
    """A model whose network file is damaged is refused in one line at once, not after the
    exact reference has trained (minutes at the default size)."""
    import shutil
    from pathlib import Path

    import apcg_core
    model = tmp_path / "broken"
    shutil.copytree(Path(apcg_core.__file__).parent / "models" / "default", model)
    data = (model / "sheets.onnx").read_bytes()
    (model / "sheets.onnx").write_bytes(data[:len(data) // 2])
    out = _cli("--source", str(model), "--train-per-type", "4", "--test-per-type", "2",
               "--epochs", "1", "--networks", "1", "-o", str(tmp_path / "r"))
    assert out.returncode == 2, out.stderr
    assert "sheets.onnx cannot be loaded" in out.stderr and "Traceback" not in out.stderr
    assert "training on" not in out.stderr and "exact test clouds" not in out.stderr
    assert not (tmp_path / "r").exists()


def test_shuffled_labels_score_chance_while_true_labels_learn():
    rep = recognize.run("exact", shuffle_labels=True, seed=1, **SMALL)
    (src,) = rep["sources"]
    assert rep["trained_on_exact"]["top1"] > 0.7
    assert src["trained_on_source"]["top1"] < rep["chance"] + 0.2
    assert src["tstr"]["overall"]["ratio"] < 0.7


def test_a_source_of_pure_noise_scores_chance():
    rep = recognize.run(["noise", "exact"], seed=2, **SMALL)
    noise, exact = rep["sources"]
    assert noise["source"]["kind"] == "noise" and exact["source"]["source"] == "exact"
    assert rep["trained_on_exact"]["top1"] > 0.7
    assert noise["trained_on_source"]["top1"] < rep["chance"] + 0.2
    # exact against exact scores its own accuracy
    assert exact["trained_on_source"] == rep["trained_on_exact"]
    assert exact["tstr"]["overall"]["ratio"] == 1.0


def test_noise_clouds_carry_nothing_of_their_rows_range():
    # half the rows a drone's at 300 m, half an aircraft's at 10 km: a noise cloud's range is
    # a row drawn at random, so drone rows get aircraft ranges as often as aircraft rows do
    table = np.zeros((400, 6))
    table[:, 0] = np.arange(400) % 2
    table[:, 1] = np.where(table[:, 0] == 0, 300.0, 10000.0)
    table[:, 2] = np.radians(3.5)
    clouds = recognize.noise_clouds(table, seed=5)
    far = np.array([np.median(np.linalg.norm(c, axis=1)) > 3000.0 for c in clouds])
    drone, aircraft = far[table[:, 0] == 0].mean(), far[table[:, 0] == 1].mean()
    assert 0.35 < drone < 0.65 and 0.35 < aircraft < 0.65
    assert far.sum() == 200  # the rows' own ranges, permuted: none lost or made up
    again = recognize.noise_clouds(table, seed=5)
    assert all(np.array_equal(a, b) for a, b in zip(clouds, again, strict=True))


def test_pure_noise_scores_chance_on_a_drone_against_an_aircraft():
    # told apart by range alone (100-600 m against 3-18 km): noise placed at its own row's
    # range scored 100% here; placed at a random row's, it learns nothing of the type
    two = {**SMALL, "types": ["777-300ER", "Mavic 3"], "epochs": 40}
    for seed in (1, 3):
        rep = recognize.run(["noise"], seed=seed, **two)
        assert rep["trained_on_exact"]["top1"] > 0.9
        assert rep["sources"][0]["trained_on_source"]["top1"] <= rep["chance"] + 0.2


def test_a_classifier_trained_on_one_type_never_exceeds_one_in_k():
    rep = recognize.run("exact", train_types=["F-16C Fighting Falcon"], seed=4, **SMALL)
    assert rep["sizes"]["source_train_clouds"] == 30
    assert rep["sizes"]["train_clouds"] == 90  # the exact reference keeps every type
    assert rep["sources"][0]["trained_on_source"]["top1"] <= rep["chance"] + 1e-9
    assert rep["trained_on_exact"]["top1"] > rep["chance"]


def test_tstr_bootstrap_interval_brackets_the_ratio():
    rng = np.random.default_rng(0)
    hit_e = rng.random(400) < 0.9
    hit_s = hit_e & (rng.random(400) < 0.8)
    bands = ["aircraft 3-6 km"] * 200 + ["drone 100-225 m"] * 200
    t = recognize.tstr(hit_s, hit_e, bands, seed=0, n_boot=500)
    lo, hi = t["overall"]["ci"]
    assert lo < t["overall"]["ratio"] < hi and 0.7 < lo and hi < 0.9
    assert list(t["bands"]) == ["aircraft 3-6 km", "drone 100-225 m"]


def test_several_networks_average_their_hits_and_the_first_is_the_one_seed_run():
    one = recognize.run("noise", seed=6, **SMALL)
    three = recognize.run("noise", seed=6, **{**SMALL, "networks": 3})
    e1, e3 = one["trained_on_exact"], three["trained_on_exact"]
    # the first network is the one-network benchmark's: the same seed, the same classifier
    assert e3["networks"][0] == e1["top1"] and len(set(recognize.network_seeds(6, 3))) == 3
    assert e3["top1"] == pytest.approx(np.mean(e3["networks"]), abs=1e-6)
    assert np.asarray(e3["confusion"]).sum() == 3 * e1["n"]
    # the bands split the same averaged hits: their top-1s, weighed by their clouds, give it
    assert set(e3["bands"]) == set(e1["bands"])
    assert e3["top1"] == pytest.approx(sum(v["n"] * v["top1"] for v in e3["bands"].values())
                                       / e3["n"], abs=1e-5)
    # the ratio is of the averaged hits: pure noise stays near chance whatever the count
    assert three["sources"][0]["trained_on_source"]["top1"] < three["chance"] + 0.2


def test_networks_below_one_is_refused():
    from apcg_core.errors import InputError
    with pytest.raises(InputError, match="networks"):
        recognize.run("exact", seed=0, **{**SMALL, "networks": 0})
