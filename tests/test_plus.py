"""APCG+ (apcg_core/families/apcg_plus.py, training/families/apcg_plus.py): its geometry agrees
with torch and with the simulator's box, it trains, exports, loads and generates like every
family, and it learns."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from apcg_core.errors import InputError
from apcg_core.families import load_model
from apcg_core.families.apcg_plus import (
    PlusModel,
    box_cells,
    box_half_cells,
    sample_sheets,
    sheet_coords,
)
from training import protocol
from training.data import DepthDataset
from training.export import export_model
from training.trainer import Trainer, config_from

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def trained(tiny_training_data, tmp_path_factory):
    """A small APCG+ trained briefly on the tiny dataset, exported, with its untrained twin."""
    tmp = tmp_path_factory.mktemp("plus")
    cfg = config_from("tiny", family="apcg-plus", steps=400, seed=3, width=0.25, sheet=32,
                      checkpoint_every=10**6, log_every=100)
    assert (cfg.lr, cfg.n_critic) == (1e-3, 1)  # the family's own defaults over the preset's
    Trainer(tiny_training_data, tmp / "run", cfg, progress=False).fit()
    model = load_model(export_model(tmp / "run", tmp / "model"))
    return model, protocol.untrained(model, tmp / "untrained")


def test_bilinear_reads_equal_torch_grid_sample():
    rng = np.random.default_rng(0)
    sheets = rng.standard_normal((3, 2, 16, 16)).astype(np.float32)
    sample = rng.integers(0, 3, 500)
    u, v = rng.uniform(-1.3, 1.3, 500), rng.uniform(-1.3, 1.3, 500)  # border reads included
    got = sample_sheets(sheets, sample, u, v)
    grid = torch.zeros(3, 500, 1, 2)
    want = np.zeros((500, 2))
    for s in range(3):
        sel = np.flatnonzero(sample == s)
        g = torch.from_numpy(np.stack([u[sel], -v[sel]], -1).astype(np.float32))[None, :, None]
        out = torch.nn.functional.grid_sample(torch.from_numpy(sheets[s:s + 1]), g,
                                              mode="bilinear", padding_mode="border",
                                              align_corners=False)
        want[sel] = out[0, :, :, 0].T.numpy()
    del grid
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_every_standard_return_lies_in_the_box(tiny_training_data):
    """The box generation reads covers every cell the simulator returned, on every sample."""
    for split in ("train", "test"):
        ds = DepthDataset(tiny_training_data, split)
        rad = np.array([r["bounding_radius_m"] for r in ds.types.records])[
            ds.conditions[:, 0].astype(int)]
        w_half, h_half = box_half_cells(ds.conditions[:, 1], ds.conditions[:, 2], rad, ds.lidar)
        for i in range(len(ds)):
            c = ds.sample_cloud(i)
            assert (np.abs(c.cell_w) <= w_half[i]).all() and (np.abs(c.cell_h) <= h_half[i]).all()
            u, v = sheet_coords(c.cell_w, c.cell_h, ds.conditions[i, 1], ds.conditions[i, 2],
                                rad[i], ds.lidar)
            assert (np.hypot(u, v) <= 1.01).all()  # returns sit within R of the centre


def test_query_mixes_draw_returns_or_places(tiny_training_data):
    """`--queries`: the returns mix draws a quarter of its cells among the returns (all hits);
    the silhouette mix draws none because they are returns, so fewer of its cells are hits;
    the box quarter (drawn first) is the same cells in both."""
    from training.families.apcg_plus import QUERIES, QUERY_MIXES, draw_queries
    ds = DepthDataset(tiny_training_data, "train")
    idx = np.arange(min(len(ds), 16))
    got = {mix: draw_queries(ds, idx, np.random.default_rng(5), mix=mix) for mix in QUERY_MIXES}
    n_box, n_hit = QUERIES // 4, QUERIES // 4
    has_returns = np.array([len(ds.sample_cloud(int(i)).cell_w) > 0 for i in idx])
    assert has_returns.any()
    u, v, hit, _ = got["returns"]
    assert hit[has_returns, n_box:n_box + n_hit].all()
    su, sv, shit, _ = got["silhouette"]
    assert u.shape == su.shape == (len(idx), QUERIES)
    assert np.array_equal(u[:, :n_box], su[:, :n_box]) and np.array_equal(v[:, :n_box],
                                                                           sv[:, :n_box])
    assert shit[has_returns].mean() < hit[has_returns].mean() - 0.1
    assert shit[has_returns, n_box:].mean() > 0.2  # still mostly near the silhouette
    with pytest.raises(KeyError):
        draw_queries(ds, idx, np.random.default_rng(5), mix="labels")


def test_box_cells_are_clipped_to_the_window():
    from apcg_core.lidar import LidarParams
    lidar = LidarParams()
    # a 40 m radius at 3 km spans more than the 64 rows: the box stops at the window
    sample, w, h = box_cells(np.array([3000.0, 18000.0]), np.array([0.06, 0.06]),
                             np.array([40.0, 40.0]), lidar)
    assert lidar.inside(w, h).all()
    assert (h[sample == 0].min(), h[sample == 0].max()) == (-32, 31)
    assert (sample == 1).sum() < (sample == 0).sum()  # far: fewer cells to read


def test_trained_model_beats_its_untrained_network(trained, tiny_training_data):
    model, fresh = trained
    assert model.family == "apcg-plus"
    pairs = protocol.draw_pairs(tiny_training_data, None, 0, "test")
    got = protocol.score(model, pairs, floor=False, pointflow=False)
    base = protocol.score(fresh, pairs, floor=False, pointflow=False)
    scored = [sum(b["scored"] for b in r["bands"].values()) for r in (got, base)]
    assert scored[0] > 0
    if base["mean"]["mmd"] is not None:
        assert got["mean"]["mmd"] < base["mean"]["mmd"], (got["mean"], base["mean"])
    else:  # the untrained sheets stay below tau everywhere: nothing to score
        assert scored[1] == 0
    ratios = [b["points_ratio_p10_p50_p90"][1] for b in got["bands"].values()]
    assert all(r is not None and 0.3 < r < 3.0 for r in ratios), ratios


def test_onnx_and_torch_runtimes_agree(trained, tiny_training_data):
    model, _ = trained
    other = PlusModel(model.directory, runtime="torch")
    cond = DepthDataset(tiny_training_data, "test").condition_rows(np.arange(6))
    a, b = model.generate(cond), other.generate(cond)
    np.testing.assert_allclose(model.sheets(a.table), other.sheets(b.table), atol=1e-4)
    assert abs(len(a.cloud) - len(b.cloud)) <= 0.01 * len(a.cloud) + 2
    # the condition decides the cloud: the seed changes nothing
    again = model.generate(cond, seed=99)
    np.testing.assert_array_equal(again.cloud.xyz, a.cloud.xyz)
    # ranges sit on the lidar's time bins, as the standard data's do
    bins = a.cloud.range_m / model.lidar.r_r - 0.5
    np.testing.assert_allclose(bins, np.round(bins), atol=1e-6)


def test_clouds_come_back_one_per_condition_in_order(trained, tiny_training_data):
    model, _ = trained
    ds = DepthDataset(tiny_training_data, "test")
    cond = ds.condition_rows(np.arange(5))
    res = model.generate(cond, count=2)
    assert len(res.conditions.table) == 10
    clouds = res.cloud.split(10)
    for k, c in enumerate(clouds):
        if len(c):
            r = np.linalg.norm(c.xyz, axis=1)
            assert abs(np.median(r) - res.table[k, 1]) < 60.0  # about the condition's range


def test_refuses_types_it_does_not_know_and_broken_model_json(trained, tmp_path):
    model, _ = trained
    with pytest.raises(InputError, match="Cessna 172"):
        model.condition("Cessna 172", 5000.0, 0.06)
    meta = dict(model.meta)
    meta["types"] = [{k: v for k, v in t.items() if k != "bounding_radius_m"}
                     for t in meta["types"]]
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "model.json").write_text(json.dumps(meta))
    (bad / "sheets.onnx").write_bytes((Path(model.directory) / "sheets.onnx").read_bytes())
    with pytest.raises(InputError, match="bounding_radius_m"):
        load_model(bad)
    with pytest.raises(InputError, match="sheets.onnx"):
        (bad / "sheets.onnx").unlink()
        load_model(bad)


def test_generate_command_writes_its_clouds(trained, tmp_path):
    model, _ = trained
    name = model.types.names[0]
    out = tmp_path / "c.npz"
    r = subprocess.run([sys.executable, "-m", "apcg_core.cli", "generate", "--model",
                        str(model.directory), "--type", name, "--range-m",
                        str(model.space.aircraft_range_m[0] + 500.0), "--elevation-deg", "3.5",
                        "--pitch-deg", "2", "-o", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    with np.load(out) as f:
        assert len(f["xyz"]) > 0


def test_sheet_size_is_checked():
    from apcg_core.nn.apcg_plus import PlusConfig
    for bad in (0, 48, 100, 4096):
        with pytest.raises(InputError, match="sheet"):
            PlusConfig(n_types=2, sheet=bad)


def test_choose_tau_sweeps_the_hit_logit_on_the_validation_half(trained, tiny_training_data):
    model, _ = trained
    rep = protocol.choose_tau(model, tiny_training_data, n_pairs=40)
    assert rep["half"] == "validation"
    assert set(rep["taus"]) == {f"{t:g}" for t in model.TAUS}
    assert rep["best"] in model.TAUS and model.tau == 0.0  # the sweep leaves the model as it was
    counts = [rep["taus"][f"{t:g}"]["points_ratio_median_mean_over_bands"] for t in model.TAUS]
    assert counts == sorted(counts, reverse=True)  # a higher threshold keeps fewer returns
    for bad in (float("nan"), float("inf"), "1"):
        with pytest.raises(InputError, match="tau"):
            model.check_tau(bad)


def _read_every_box_cell(model, table, sheets):
    """The reference reader: every cell of every box, bilinear, drawn by the model's draw
    over whole box rows (w ascending from the box's first cell)."""
    codes = table[:, 0].astype(int)
    r0, b0, rad = table[:, 1], table[:, 2], model.radius[codes]
    sample, w, h = box_cells(r0, b0, rad, model.lidar)
    order = np.lexsort((w, h, sample))
    sample, w, h = sample[order], w[order], h[order]
    u, v = sheet_coords(w, h, r0[sample], b0[sample], rad[sample], model.lidar)
    read = sample_sheets(sheets, sample, u, v)
    keep = model.draw.keep(sample, h, read[:, 0], model.tau)
    r = model.lidar.quantize_range(r0[sample[keep]] + read[keep, 1] * rad[sample[keep]])
    return sample[keep], w[keep], h[keep], r


@pytest.mark.parametrize("draw", ["threshold", "diffuse-rows"])
@pytest.mark.parametrize("kind", ["trained", "random", "speckled"])
def test_fast_reader_finds_every_return_of_the_full_box(trained, tiny_training_data, kind,
                                                        draw):
    """The interval reader equals reading every box cell, on trained sheets and on sheets
    with many separate blobs per row (where one interval per row must still cover them),
    under each draw (the diffused one counts every cell outside the intervals as p = 0)."""
    from apcg_core.families.plus_draw import DRAWS
    model, _ = trained
    own = model.draw
    model.draw = DRAWS[draw]
    try:
        _fast_reader_against_full_box(model, tiny_training_data, kind)
    finally:
        model.draw = own


def _fast_reader_against_full_box(model, tiny_training_data, kind):
    ds = DepthDataset(tiny_training_data, "test")
    table = model.repeated_conditions(ds.condition_rows(np.arange(len(ds))), 1)
    sheets = model.sheets(table)
    rng = np.random.default_rng(1)
    if kind == "random":
        sheets = rng.normal(-1.0, 2.0, sheets.shape).astype(np.float32)
    elif kind == "speckled":
        sheets = np.where(rng.random(sheets.shape) < 0.03, 5.0, -5.0).astype(np.float32)
    for tau in (0.0, 1.3):
        model.tau = tau
        try:
            got = model.clouds_of(table, sheets)
            want = _read_every_box_cell(model, table, sheets)
        finally:
            model.tau = 0.0
        assert len(want[0]) > 0
        key = lambda s, w, h: np.lexsort((h, w, s))  # noqa: E731
        g, k = key(got.sample, got.cell_w, got.cell_h), key(*want[:3])
        np.testing.assert_array_equal(got.sample[g], want[0][k])
        np.testing.assert_array_equal(got.cell_w[g], want[1][k])
        np.testing.assert_array_equal(got.cell_h[g], want[2][k])
        np.testing.assert_allclose(got.range_m[g], want[3][k], rtol=0, atol=1e-9)


def test_teach_adds_a_type_and_leaves_the_known_ones_exactly(trained, tiny_training_data,
                                                             tmp_path):
    from training.teach import teach
    model, _ = trained
    rep = teach(model.directory, "777-300ER", tmp_path / "taught", samples=24, steps=30,
                data_dir=tmp_path / "data", progress=False)
    new = load_model(tmp_path / "taught")
    assert new.types.names == [*model.types.names, "777-300ER"]
    assert rep["fit"]["steps"] == 30 and rep["score"]["pairs"] > 0
    assert json.loads((tmp_path / "taught" / "teach.json").read_text())["type"] == "777-300ER"
    # the types it knew generate exactly as before (their weights are untouched)
    cond = DepthDataset(tiny_training_data, "test").condition_rows(np.arange(6))
    np.testing.assert_array_equal(new.generate(cond).cloud.xyz, model.generate(cond).cloud.xyz)
    got = new.generate(new.condition("777-300ER", 6000.0, 0.06, pitch=0.03))
    assert len(got.cloud) > 0
    with pytest.raises(InputError, match="already knows"):
        teach(tmp_path / "taught", "777-300ER", tmp_path / "again", samples=24, steps=1,
              progress=False)
    with pytest.raises(InputError, match="not empty"):
        teach(model.directory, "777-300ER", tmp_path / "taught", samples=24, steps=1,
              progress=False)
    with pytest.raises(InputError, match="No Such Jet"):
        teach(model.directory, "No Such Jet", tmp_path / "x", samples=24, steps=1,
              progress=False)


def test_figure_16_sets_generated_beside_standard(trained, tmp_path):
    from training.figures import fig16
    model, _ = trained
    data = fig16(model, tmp_path / "fig16.png", types=("A320neo", "Mavic 3"))
    assert (tmp_path / "fig16.png").stat().st_size > 10_000
    assert [(p["type"], p["range_m"]) for p in data["panels"]] == [
        ("A320neo", 4500.0), ("A320neo", 9000.0), ("A320neo", 15000.0),
        ("Mavic 3", 150.0), ("Mavic 3", 350.0), ("Mavic 3", 550.0)]
    assert all(p["points_standard"] > 0 for p in data["panels"])


@pytest.mark.parametrize("draw", ["threshold", "diffuse-rows"])
@pytest.mark.parametrize("kind", ["shipped", "speckled"])
def test_device_reader_equals_the_package_reader(monkeypatch, kind, draw):
    """nn.apcg_plus.read_clouds (the reader that runs where the sheets are, bench/
    gpu_generate.py) returns the numpy reader's cells, ranges and points, in its order, on
    the shipped model's sheets at random conditions of every type (near and far, drones), and
    on speckled sheets; in groups of a few box cells (READ_CELLS) as in one."""
    import torch

    from apcg_core.families.apcg_plus import box_half_cells
    from apcg_core.families.plus_draw import DRAWS
    from apcg_core.nn import apcg_plus as nn_plus
    model = load_model(None)
    model.draw = DRAWS[draw]
    rng = np.random.default_rng(7)
    n = 96
    table = model.space.decode(rng.uniform(-1, 1, (n, 6)))
    table[:, 0] = rng.integers(0, len(model.types.names), n)
    lo, hi = model.space.bounds(table)
    table[:, 1] = rng.uniform(lo[:, 1], hi[:, 1])
    table[:4, 1] = lo[:4, 1]  # the nearest: boxes larger than the window
    sheets = model.sheets(table)
    if kind == "speckled":
        sheets = np.where(rng.random(sheets.shape) < 0.03, 5.0, -5.0).astype(np.float32)
    want = model.clouds_of(table, sheets)
    rad = model.radius[table[:, 0].astype(int)]
    box = box_half_cells(table[:, 1], table[:, 2], rad, model.lidar)
    assert len(want.range_m) > 1000
    for group in (nn_plus.READ_CELLS, 5000):
        monkeypatch.setattr(nn_plus, "READ_CELLS", group)
        xyz, r, w, h, sample = (t.numpy() for t in nn_plus.read_clouds(
            torch.from_numpy(sheets), table[:, 1], table[:, 2], rad, box, model.lidar,
            model.tau, model.quantize, model.draw))
        np.testing.assert_array_equal(sample, want.sample)
        np.testing.assert_array_equal(w, want.cell_w)
        np.testing.assert_array_equal(h, want.cell_h)
        np.testing.assert_allclose(r, want.range_m, rtol=0, atol=1e-9)
        np.testing.assert_allclose(xyz, want.xyz, rtol=0, atol=1e-6)


@pytest.mark.parametrize("threads", ["1", "2"])
def test_the_sheets_are_the_same_bytes_at_any_network_batch(threads, monkeypatch):
    """The network runs NET_ROWS conditions a call within a block: the shipped default's sheets
    are byte for byte those of one call per condition, of odd and even batches or of the whole
    block in one call (onnxruntime on its own threads, or one thread a lane), so the batch is a
    speed setting and a condition's cloud is the same alone or among others."""
    monkeypatch.setenv("APCG_THREADS", threads)
    from apcg_core.families.apcg_plus import NET_ROWS
    model = load_model()
    rng = np.random.default_rng(8)
    names = [model.types.records[i]["name"] for i in rng.integers(0, 83, 70)]
    pose = np.column_stack([rng.uniform(3000, 18000, 70), np.radians(rng.uniform(3, 4, 70)),
                            np.radians(rng.uniform(1, 5, 70)), np.radians(rng.uniform(-60, 60, 70)),
                            np.radians(rng.uniform(-5, 5, 70))])
    table = model.repeated_conditions(model.conditions(names, pose), 1)
    want = model.sheets(table)
    assert want.shape == (70, 2, 32, 32) and NET_ROWS < 70
    for rows in (1, 3, 7, 31, 64, 69, 70):
        assert model.sheets(table, rows=rows).tobytes() == want.tobytes(), rows
    one = model.generate(model.conditions(names[5:6], pose[5:6])).cloud
    among = model.generate(model.conditions(names, pose)).cloud
    assert one.xyz.tobytes() == among.xyz[among.sample == 5].tobytes()
