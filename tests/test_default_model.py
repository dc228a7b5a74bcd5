"""The default model that ships in the package: its files, its size, and that it is a trained
model: run here at fresh conditions, simulated here with embree, it beats its own untrained
network."""

import json

import numpy as np
import pytest

from apcg_core.catalog.catalog import default_catalog
from apcg_core.generation import APCGModel, default_model_dir
from apcg_core.typetable import Conditions
from dataset_builder.simulate import Simulator
from training import protocol

MODEL = default_model_dir()


def test_default_model_files_and_size():
    names = {p.name for p in MODEL.iterdir()}
    assert {"model.json", "generator.onnx", "log.csv", "train_config.json",
            "evaluation.json", "tau_sweep.json"} <= names
    size = sum(p.stat().st_size for p in MODEL.iterdir())
    assert size <= 5 * 2**20, f"the default model takes {size / 2**20:.2f} MB (at most 5)"
    meta = json.loads((MODEL / "model.json").read_text())
    sweep = json.loads((MODEL / "tau_sweep.json").read_text())
    assert meta["tau"] == pytest.approx(sweep["best"])  # tau is the measured one
    assert sweep["half"] == "validation"  # chosen where the reported scores are not
    assert meta["trained_steps"] > 0 and meta["net"]["width"] == 0.25
    assert len(meta["types"]) == len(default_catalog().types)  # every catalog type
    # the log covers every trained step
    last = (MODEL / "log.csv").read_text().strip().splitlines()[-1]
    assert int(last.split(",")[0]) == meta["trained_steps"]


def _conditions(model, names, rng, n):
    cat = default_catalog()
    rows, refs = [], []
    with Simulator("embree", model.lidar) as sim:
        for name in names:
            t = cat.get(name)
            near = t.range_band == "near"
            lo, hi = (100.0, 600.0) if near else (3000.0, 18000.0)
            table = np.column_stack([
                np.full(n, model.types.code(name)), rng.uniform(lo, hi, n),
                np.radians(rng.uniform(3, 4, n)), np.radians(rng.uniform(1, 5, n)),
                np.radians(rng.uniform(-60, 60, n)), np.radians(rng.uniform(-5, 5, n))])
            refs += [c.xyz for c in sim.simulate_type(cat, t.name, table).clouds()]
            rows.append(table)
    return Conditions(model.types, np.concatenate(rows)), refs


def test_default_model_beats_its_untrained_network_at_fresh_conditions(tmp_path):
    model = APCGModel(runtime="onnx")
    untrained = protocol.untrained(model, tmp_path / "untrained")
    rng = np.random.default_rng(2026)
    table, refs = _conditions(model, ["A320neo", "777-300ER", "Mavic 3"], rng, 12)
    scores = {}
    for label, m in (("trained", model), ("untrained", untrained)):
        clouds = m.generate(table, seed=5).cloud.split(len(table))
        pairs = [(r, c.xyz) for r, c in zip(refs, clouds, strict=True) if len(r) and len(c)]
        assert len(pairs) >= 0.9 * len(table), f"{label}: too many empty clouds"
        rows = [protocol.score_pair(a, b, seed=0) for a, b in pairs]
        scores[label] = (np.mean([r["mmd"] for r in rows]), np.mean([r["jsd"] for r in rows]))
    assert scores["trained"][0] < scores["untrained"][0], scores
    assert scores["trained"][1] < scores["untrained"][1], scores


def test_default_model_torch_and_onnx_agree():
    table = np.array([[0, 9000.0, np.radians(3.5), 0.05, 0.3, 0.0]])
    onnx, torch_m = APCGModel(runtime="onnx"), APCGModel(runtime="torch")
    table[0, 0] = onnx.types.code("A320neo")
    noise = np.random.default_rng(0).standard_normal((1, 100))
    nu = onnx.space.encode(table)
    assert np.abs(onnx.images_from(noise, nu) - torch_m.images_from(noise, nu)).max() < 1e-4
