"""The faithfulness score (training/faithfulness.py, SPEC section 9): a generated cloud is
faithful when it is closer (MMD) to its own standard cloud than to the same type at yaw
+-45 deg and to a type of another category; real embree, a real small dataset."""

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from apcg_core.catalog import default_catalog
from apcg_core.errors import InputError
from apcg_core.typetable import TypeTable
from dataset_builder.build import build_dataset
from dataset_builder.simulate import Simulator
from training import faithfulness as fa
from training import protocol
from training.data import DepthDataset

THREE = ["Mavic 3", "UH-60 Black Hawk", "A320neo"]  # multirotor, helicopter, airliner


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("faith") / "ds"
    cfg = {"description": "faithfulness tests", "seed": 11, "backend": "embree",
           "shard_size": 100, "test_fraction": 0.5, "quantize": True, "supersample": 1,
           "sampling": "grid", "types": THREE,
           "counts": {"elevation": 1, "range_m": 3, "yaw": 4, "pitch": 2, "roll": 2}}
    build_dataset(cfg, out, progress=False)
    return out


@pytest.fixture(scope="module")
def pairs(data):
    return protocol.draw_pairs(data, None, seed=3, half="test")


@pytest.fixture(scope="module")
def prepared(pairs):
    return fa.prepare(pairs)


class Clouds:
    """A 'generator' that returns the clouds ``make(ds, dataset rows)`` gives, whatever the
    seed: the protocol scores it as it scores a model."""

    def __init__(self, ds, make, name):
        self.ds, self.make = ds, make
        self.directory, self.family, self.tau = name, "test", None

    def generate(self, conditions, count=1, seed=0):
        assert conditions.types.names == self.ds.types.names  # the dataset's own table
        clouds = self.make(self.ds, conditions.table)
        return SimpleNamespace(cloud=SimpleNamespace(
            split=lambda n: [SimpleNamespace(xyz=c) for c in clouds]))


def _standard(ds, table):
    # the stored standard cloud of the sample with this exact condition row
    return [ds.standard_cloud(int(np.flatnonzero((ds.conditions == row).all(axis=1))[0]))
            for row in table]


def _yawed(ds, table):
    # the yaw decoy made independently of the module: embree, yaw 45 deg toward zero
    cat = default_catalog()
    rows = np.array(table, dtype=float)
    rows[:, 4] -= np.sign(rows[:, 4] + (rows[:, 4] == 0)) * math.radians(45)
    with Simulator("embree", ds.lidar) as sim:
        return [sim.simulate_type(cat, ds.types.name(int(r[0])), r[None]).clouds()[0].xyz
                for r in rows]


def test_the_standard_clouds_are_faithful(pairs, prepared):
    rep = protocol.score(Clouds(pairs.ds, _standard, "standard"), pairs, floor=False,
                         pointflow=False, faithfulness=prepared)
    scorable = 0
    for name, b in rep["bands"].items():
        f = b["faithfulness"]
        assert f["pairs"] == b["pairs"] and f["too_few_points"] == 0
        scorable += f["scorable"]
        if f["scorable"]:
            assert f["share"] == f["share_vs_yaw"] == f["share_vs_other_type"] == 1.0, name
            assert f["faithful"] == f["scorable"]
    assert scorable >= 20  # enough pairs were really judged
    assert rep["mean"]["faithfulness"]["all"] == 1.0
    assert rep["mean"]["faithfulness"]["aircraft"] == rep["mean"]["faithfulness"]["drone"] == 1.0
    for p in rep["per_pair"]:
        assert p["faithful"] is (None if p["n_standard"] < protocol.MIN_POINTS else True)
        assert p["decoy_type"] in default_catalog().names() and p["decoy_type"] != p["type"]
    # the references, scored on the same pairs as a model is
    assert set(rep["references"]) == {"points", "embree 2x2"}
    for r in rep["references"].values():
        assert r["bands"].keys() == rep["bands"].keys()
        for name, b in r["bands"].items():
            assert b["pairs"] == rep["bands"][name]["pairs"]
            assert {"mmd", "jsd", "points_ratio_p10_p50_p90"} <= b.keys()
            assert 0.0 <= b["faithfulness"]["share"] <= 1.0


def test_the_yaw_decoy_as_generator_is_not_faithful(pairs, prepared):
    rep = protocol.score(Clouds(pairs.ds, _yawed, "yawed"), pairs, floor=False,
                         pointflow=False, faithfulness=prepared)
    judged = [p for p in rep["per_pair"] if p["faithful"] is not None]
    assert len(judged) >= 20
    vs_yaw = np.mean([p["closer_than_yaw"] for p in judged])
    assert vs_yaw <= 0.05, vs_yaw
    assert not any(p["faithful"] for p in judged)
    # MMD to the yaw decoy is (nearly) zero: the module's decoy is the test's shifted cloud
    assert np.median([p["mmd_yaw"] for p in judged]) < 1e-3


def test_empty_and_sparse_clouds_count_as_not_faithful(pairs, prepared):
    def empty(ds, table):
        return [np.zeros((0, 3)) for _ in table]

    def sparse(ds, table):
        return [c[:protocol.MIN_POINTS - 1] for c in _standard(ds, table)]

    for make in (empty, sparse):
        rep = protocol.score(Clouds(pairs.ds, make, make.__name__), pairs, floor=False,
                             pointflow=False, faithfulness=prepared)
        f = [b["faithfulness"] for b in rep["bands"].values()]
        assert sum(x["pairs"] for x in f) == len(pairs)  # none dropped
        assert sum(x["too_few_points"] for x in f) == sum(x["scorable"] for x in f) >= 20
        assert all(x["share"] in (0.0, None) and x["faithful"] == 0 for x in f)
        assert rep["mean"]["faithfulness"]["all"] == 0.0


def test_the_other_type_decoy_is_another_category_in_the_same_band(pairs, prepared):
    cat = default_catalog()
    for name in THREE + ["F-16C Fighting Falcon", "MQ-9A Reaper", "eBee X"]:
        own = cat.get(name)
        picks = [fa.decoy_type(name, s) for s in range(40)]
        assert picks == [fa.decoy_type(name, s) for s in range(40)]  # reproducible
        assert len(set(picks)) > 1  # a real draw
        for p in picks:
            t = cat.get(p)
            assert t.category != own.category and t.range_band == own.range_band
    # the prepared decoys: the drawn types, simulated at the pair's own condition
    ds = pairs.ds
    d = prepared.decoys
    for j, i in enumerate(pairs.idx[:6]):
        own = ds.types.name(int(ds.conditions[i, 0]))
        assert d.other_type[j] == fa.decoy_type(own, pairs.seed + j)
        with Simulator("embree", ds.lidar) as sim:
            again = sim.simulate_type(cat, d.other_type[j], ds.conditions[i][None])
        assert np.array_equal(again.clouds()[0].xyz, d.other[j])


def test_an_unknown_type_is_refused_by_name(data):
    ds = DepthDataset(data, "test")
    ds.types = TypeTable.from_records(
        [{"name": "My Glider", "depth_length_m": 8.0}] + ds.types.to_records()[1:],
        owner="dataset x")
    idx = np.flatnonzero(ds.conditions[:, 0] == 0)[:2]
    with pytest.raises(InputError, match="holds type 'My Glider', which the catalog does not "
                                         "know"):
        fa.decoys(ds, idx, [0, 1])
    with pytest.raises(InputError, match="My Glider"):
        fa.simulated("points", ds, idx)
    with pytest.raises(InputError, match="unknown aircraft type 'My Glider'"):
        fa.decoy_type("My Glider", 0)


def test_prepared_decoys_refuse_other_pairs(data, prepared):
    other = protocol.draw_pairs(data, 5, seed=9, half="test")
    with pytest.raises(InputError, match="prepared for other pairs"):
        protocol.score(Clouds(other.ds, _standard, "s"), other, floor=False, pointflow=False,
                       faithfulness=prepared)


def test_apcg_evaluate_reports_faithfulness_and_can_skip_it(data, tmp_path):
    from apcg_core.cli import main
    assert main(["evaluate", "--data", str(data), "-o", str(tmp_path / "on"), "--pairs", "30",
                 "--runtime", "onnx"]) == 0
    rep = json.loads((tmp_path / "on" / "metrics.json").read_text())
    md = (tmp_path / "on" / "report.md").read_text()
    assert set(rep["references"]) == {"points", "embree 2x2"}
    assert set(rep["mean"]["faithfulness"]) == {"all", "aircraft", "drone"}
    assert "faithfulness" in rep["seconds"]
    for name, b in rep["bands"].items():
        line = next(ln for ln in md.split("Faithfulness (SPEC")[1].splitlines()
                    if ln.startswith(f"| {name} |"))
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[1] == str(b["pairs"]) and len(cells) == 12
        assert cells[6] == " / ".join(f"{v:.2f}" for v in b["points_ratio_p10_p50_p90"])
        if b["faithfulness"]["share"] is not None:
            assert cells[7].startswith(f"{100 * b['faithfulness']['share']:.0f}%")
    assert main(["evaluate", "--data", str(data), "-o", str(tmp_path / "off"), "--pairs", "30",
                 "--runtime", "onnx", "--no-faithfulness"]) == 0
    off = json.loads((tmp_path / "off" / "metrics.json").read_text())
    assert "references" not in off and "faithfulness" not in off["mean"]
    assert "Faithfulness (SPEC" not in (tmp_path / "off" / "report.md").read_text()
    # the rest of the report does not change with faithfulness
    assert [{k: p[k] for k in ("sample_id", "mmd", "jsd")} for p in off["per_pair"]] == \
        [{k: p[k] for k in ("sample_id", "mmd", "jsd")} for p in rep["per_pair"]]


def test_compare_shows_each_methods_faithfulness_beside_the_references(data):
    from apcg_core.families import load_model
    from training.compare import compare, markdown
    model = load_model(runtime="onnx")
    rep = compare([("one", model), ("two", model)], data, n_pairs=30, memory_steps=0,
                  with_untrained=False)
    rep["command"] = "apcg compare ..."
    alone = protocol.score(model, protocol.draw_pairs(data, 30, 0, "test"), floor=False,
                           pointflow=False, faithfulness=True)  # decoys made afresh
    for r in rep["rows"]:
        assert {b: v["faithfulness"] for b, v in r["bands"].items()} == \
            {b: v["faithfulness"] for b, v in alone["bands"].items()}
        assert r["mean"]["faithfulness"] == alone["mean"]["faithfulness"]

    def untimed(refs):
        return {k: {kk: vv for kk, vv in v.items() if kk != "ms_per_cloud"}
                for k, v in refs.items()}
    assert untimed(rep["references"]) == untimed(alone["references"])
    table = markdown(rep).split("Faithfulness (SPEC")[1]
    for method in ("one", "two", "points (reference)", "embree 2x2 (reference)"):
        line = next(ln for ln in table.splitlines() if ln.startswith(f"| {method} |"))
        assert line.count("|") == len(rep["rows"][0]["bands"]) + 3
