"""The evaluation protocol (training/protocol.py) and the type identity it rests on: a dataset's
types reach a model by name, whatever either side's order; pairs, halves and scores are what the
protocol says, reproducible to the digit."""

import math

import numpy as np
import pytest

from apcg_core.errors import InputError
from apcg_core.families import default_model_dir, load_model
from apcg_core.metrics import jsd, mmd
from apcg_core.typetable import Conditions, TypeTable
from dataset_builder.build import build_dataset
from training import protocol
from training.data import DepthDataset
from training.evaluate import evaluate, markdown, write_report

# Three types in an order unlike the catalog's (the catalog has A320neo before UH-60 before
# Mavic 3): dataset codes 0, 1, 2 are catalog-far-apart types and the default model's codes
# for them are others again.
THREE = ["Mavic 3", "UH-60 Black Hawk", "A320neo"]


@pytest.fixture(scope="module")
def three_types(tmp_path_factory):
    out = tmp_path_factory.mktemp("three") / "ds"
    cfg = {"description": "three types, shuffled order", "seed": 3, "backend": "embree",
           "shard_size": 100, "test_fraction": 0.5, "quantize": True, "supersample": 1,
           "sampling": "grid", "types": THREE,
           "counts": {"elevation": 2, "range_m": 3, "yaw": 2, "pitch": 2, "roll": 2}}
    build_dataset(cfg, out, progress=False)
    return out


@pytest.fixture(scope="module")
def model():
    return load_model(runtime="onnx")


def test_bands_and_band_mean():
    assert protocol.band_of(3000.0, False) == "aircraft 3-6 km"
    assert protocol.band_of(18000.0, False) == "aircraft 15-18 km"
    assert protocol.band_of(120.0, True) == "drone 100-225 m"
    assert protocol.band_of(600.0, True) == "drone 475-600 m"
    bands = {"a": {"mmd": 0.1, "jsd": None}, "b": {"mmd": 0.3, "jsd": None},
             "c": {"mmd": None, "jsd": None}}
    assert protocol.band_mean(bands, "mmd") == pytest.approx(0.2)  # a gap is not a zero
    assert protocol.band_mean(bands, "jsd") is None


def test_halves_are_disjoint_fixed_and_cover_the_held_out_split(three_types):
    ds = DepthDataset(three_types, "test")
    val, test = protocol.half_mask(ds, "validation"), protocol.half_mask(ds, "test")
    assert not (val & test).any() and (val | test).all()
    assert 0.3 < val.mean() < 0.7
    a = protocol.draw_pairs(three_types, 20, seed=1, half="validation")
    b = protocol.draw_pairs(three_types, 20, seed=1, half="test")
    assert not set(ds.sample_id[a.idx]) & set(ds.sample_id[b.idx])
    again = protocol.draw_pairs(three_types, 20, seed=1, half="validation")
    assert np.array_equal(a.idx, again.idx)  # seeded
    rec = a.record()
    assert rec["pairs"] == len(a) and sum(rec["pairs_per_band"].values()) == len(a)
    assert rec["half"] == "validation" and rec["seed"] == 1 and rec["pairs_asked"] == 20
    with pytest.raises(InputError, match="half must be one of validation, test"):
        protocol.half_mask(ds, "train")


def test_evaluate_maps_types_by_name_and_matches_scoring_by_hand(three_types, model):
    """The issue's case: a dataset whose type codes are not the model's. Every pair is scored
    against a cloud generated for the right type, as generating it by name by hand gives."""
    ds = DepthDataset(three_types, "test")
    assert ds.types.names == THREE
    assert [model.types.code(n) for n in THREE] != [0, 1, 2]  # the codes really differ
    rep = evaluate(model, three_types, n_pairs=None, seed=4)
    pairs = protocol.draw_pairs(three_types, None, seed=4, half="test")
    assert rep["pairs"] == len(pairs) <= protocol.CHUNK  # one generation chunk, seed 4
    names = [THREE[int(c)] for c in ds.conditions[pairs.idx, 0]]
    assert [p["type"] for p in rep["per_pair"]] == names
    assert set(rep["types"]) == set(names) and set(names) == set(THREE)
    by_hand = model.conditions(names, ds.conditions[pairs.idx, 1:])
    gen = model.generate(by_hand, seed=4).cloud.split(len(pairs))
    for j, p in enumerate(rep["per_pair"]):
        std = ds.standard_cloud(int(pairs.idx[j]))
        assert p["n_generated"] == len(gen[j].xyz)
        assert p["mmd"] == mmd(std, gen[j].xyz, max_points=protocol.MAX_POINTS, seed=4 + j)
        assert p["jsd"] == jsd(std, gen[j].xyz, bins=protocol.JSD_BINS,
                               max_points=protocol.MAX_POINTS, seed=4 + j)
    for name, t in rep["types"].items():
        mine = [p["mmd"] for p in rep["per_pair"] if p["type"] == name
                and min(p["n_standard"], p["n_generated"]) >= protocol.MIN_POINTS]
        assert t["mmd"] == pytest.approx(np.mean(mine))
    # the bug this replaces: dataset codes read as model codes are other types (here a drone's
    # 180 m read as an airliner's range: refused; elsewhere silently the wrong clouds)
    with pytest.raises(InputError, match="outside the configured range"):
        model.generate(Conditions(model.types, ds.conditions[pairs.idx]), seed=4)
    md = markdown({**rep, "command": "apcg evaluate ..."})
    for name in THREE:
        assert f"| {name} |" in md


def test_evaluate_on_the_demo_dataset_with_the_default_model(tmp_path, model):
    build_dataset("demo", tmp_path / "demo", progress=False)
    rep = evaluate(model, tmp_path / "demo", n_pairs=60, seed=0)
    assert rep["pairs"] >= 50 and len(rep["bands"]) >= 6
    assert set(rep["types"]) <= set(DepthDataset(tmp_path / "demo", "test").types.names)
    out = write_report({**rep, "command": "apcg evaluate ..."}, tmp_path / "rep")
    assert {p.name for p in out.iterdir()} == {"metrics.json", "report.md", "fig17.png"}
    again = evaluate(model, tmp_path / "demo", n_pairs=60, seed=0)
    assert again["per_pair"] == rep["per_pair"]  # a rerun reproduces it to the digit


def test_a_model_refuses_a_type_it_was_not_trained_on(model):
    other = TypeTable.from_records([{"name": "A320neo", "depth_length_m": 37.57},
                                    {"name": "My Glider", "depth_length_m": 8.0}],
                                   owner="dataset x")
    cond = Conditions(other, [[1, 4500.0, math.radians(3.5), 0.0, 0.0, 0.0]])
    with pytest.raises(InputError, match=r"was not trained on .*type My Glider; it knows: "
                                         r"A220-100"):
        model.generate(cond)
    with pytest.raises(InputError, match="generates from Conditions"):
        model.generate(np.array([[0, 4500.0, 0.06, 0.0, 0.0, 0.0]]))
    ok = Conditions(other, [[0, 4500.0, math.radians(3.5), math.radians(2.0), 0.0, 0.0]])
    res = model.generate(ok, seed=1)
    assert res.conditions.names == ["A320neo"]


def test_a_shifted_generator_scores_worse_and_the_floor_is_below(three_types, model):
    class Shifted:  # the same model, every cloud pushed 30 m down-range
        def __init__(self, inner):
            self.inner = inner
            self.directory, self.family, self.tau = inner.directory, inner.family, inner.tau

        def generate(self, conditions, count=1, seed=0):
            res = self.inner.generate(conditions, count, seed)
            res.cloud.xyz[:, 2] += 30.0
            return res

    pairs = protocol.draw_pairs(three_types, 40, seed=2)
    good = protocol.score(model, pairs)
    bad = protocol.score(Shifted(model), pairs)
    scored = {n: b for n, b in good["bands"].items() if b["mmd"] is not None}
    assert len(scored) >= 3  # every band of the three types that has enough points
    for name, b in scored.items():
        assert b["floor"]["mmd"] < b["mmd"] < bad["bands"][name]["mmd"]


def test_choose_tau_uses_the_validation_half_only(three_types, model):
    rep = protocol.choose_tau(model, three_types, n_pairs=20, seed=0)
    assert rep["half"] == "validation" and rep["best"] in model.TAUS  # the model's own
    assert model.tau == load_model(runtime="onnx").tau  # restored
    cgan = load_model(default_model_dir().parent / "cgan", runtime="onnx")
    rep = protocol.choose_tau(cgan, three_types, taus=(-0.99, -0.5), n_pairs=20, seed=0)
    assert rep["half"] == "validation" and rep["best"] in (-0.99, -0.5)
    with pytest.raises(InputError, match=r"tau = 1\.5 is out of range"):
        protocol.choose_tau(cgan, three_types, taus=(1.5,), n_pairs=5)
