"""How an APCG+ model draws its returns from its hit logits (apcg_core/families/plus_draw.py):
the diffused draw against its closed forms (a row keeps its summed p, rounded, spread evenly;
certain cells always, cells below the span never), on the shipped model's own rows, and the
model.json record's checks."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from apcg_core.errors import InputError
from apcg_core.families import load_model
from apcg_core.families.plus_draw import (
    DEFAULT,
    DIFFUSE_ROWS,
    DRAWS,
    HALF,
    ONE,
    STEPS_PER_LOGIT,
    THRESHOLD,
    draw_of,
)


def _logit(p):
    return np.log(p / (1.0 - p))


def _row(n, hit, sample=0, h=0):
    return np.full(n, sample), np.full(n, h), np.full(n, hit, np.float64)


@pytest.mark.parametrize("p", [0.05, 0.13, 0.25, 1 / 3, 0.4, 0.5, 0.62, 0.9])
@pytest.mark.parametrize("n", [1, 2, 7, 40, 301])
def test_a_row_of_one_probability_keeps_its_sum_rounded_and_evenly(p, n):
    sample, h, hit = _row(n, _logit(p))
    kept = DIFFUSE_ROWS.keep(sample, h, hit, 0.0)
    q = DIFFUSE_ROWS.cell_quanta(hit, 0.0)[0]
    assert abs(q / ONE - p) < 1e-3  # the table's step (1/1024 logit) is all it moves p
    want = (n * int(q) + HALF) // ONE
    assert kept.sum() == want == int(np.floor(n * q / ONE + 0.5))
    assert abs(kept.sum() - n * p) <= 0.5 + n * 1e-3
    # evenly: after every cell the row has kept its running sum, rounded
    running = (np.arange(1, n + 1) * int(q) + HALF) // ONE
    np.testing.assert_array_equal(np.cumsum(kept), running)
    gaps = np.diff(np.flatnonzero(kept))
    if len(gaps):
        assert gaps.max() - gaps.min() <= 1


def test_certain_cells_are_kept_and_cells_below_the_span_never():
    sample, h, _ = _row(50, 0.0)
    for tau in (0.0, 1.3, -0.5):
        high = DIFFUSE_ROWS.keep(sample, h, np.full(50, tau + 40.0), tau)
        low = DIFFUSE_ROWS.keep(sample, h, np.full(50, tau + DIFFUSE_ROWS.span), tau)
        nan = DIFFUSE_ROWS.keep(sample, h, np.full(50, np.nan), tau)
        assert high.all() and not low.any() and not nan.any()
    # the threshold draw is the logit above tau, cell by cell
    hit = np.linspace(-2, 2, 50)
    np.testing.assert_array_equal(THRESHOLD.keep(sample, h, hit, 0.3), hit > 0.3)


def test_rows_start_afresh_and_zero_cells_change_nothing():
    """Each run of equal (sample, h) is a row of its own; padding a row with cells below the
    span anywhere (what a reader reading more of the box adds) keeps the same cells."""
    rng = np.random.default_rng(3)
    hit = rng.normal(0.0, 1.5, 600)
    sample = np.repeat(np.arange(6), 100)
    h = np.tile(np.repeat([4, 5], 50), 6)
    kept = DIFFUSE_ROWS.keep(sample, h, hit, 0.0)
    for s in range(6):
        for hh in (4, 5):
            i = (sample == s) & (h == hh)
            alone = DIFFUSE_ROWS.keep(sample[i], h[i], hit[i], 0.0)
            np.testing.assert_array_equal(kept[i], alone)
            q = DIFFUSE_ROWS.cell_quanta(hit[i], 0.0)
            assert kept[i].sum() == (q.sum() + HALF) // ONE
    pad = np.full(37, -50.0)
    padded = np.concatenate([pad, hit[:50], pad[:5], hit[50:100]])
    ps, ph = np.zeros(len(padded), int), np.repeat([4, 5], [37 + 50 + 5, 50])
    got = DIFFUSE_ROWS.keep(ps, ph, padded, 0.0)
    np.testing.assert_array_equal(got[37:87], kept[:50])
    np.testing.assert_array_equal(got[92:], kept[50:100])
    assert not got[:37].any() and not got[87:92].any()


def test_the_table_is_the_logistic_at_each_step():
    q = DIFFUSE_ROWS.quanta
    z = DIFFUSE_ROWS.span + (np.arange(len(q) - 1) + 0.5) / STEPS_PER_LOGIT
    assert np.abs(q[:-1] / ONE - 1 / (1 + np.exp(-z))).max() <= 0.5 / ONE + 1e-12
    assert (np.diff(q) >= 0).all() and q[-1] == ONE and q[0] > 0
    assert len(THRESHOLD.quanta) == 0


def test_the_shipped_model_draws_diffused_rows_that_keep_their_sums():
    """On the shipped default's own sheets: every box row keeps its summed p, rounded (the
    numpy reader's cells: PlusModel.box_reads), and thin rows of p below one half are drawn
    in part where the threshold would draw none of them."""
    model = load_model(None)
    assert model.draw == DEFAULT == DIFFUSE_ROWS
    rng = np.random.default_rng(2)
    table = model.space.decode(rng.uniform(-1, 1, (200, 6)))
    lo, hi = model.space.bounds(table)
    table[:, 1] = rng.uniform(lo[:, 1], hi[:, 1])
    table = model.space.check(table)
    sheets = model.sheets(table)
    sample, w, h, read = model.box_reads(table, sheets, model.draw.row_floor(model.tau))
    kept = model.draw.keep(sample, h, read[:, 0], model.tau)
    q = model.draw.cell_quanta(read[:, 0], model.tau)
    row = np.unique(np.stack([sample, h], 1), axis=0, return_inverse=True)[1].ravel()
    sums = np.bincount(row, weights=q.astype(np.float64))
    counts = np.bincount(row, weights=kept)
    np.testing.assert_array_equal(counts, np.floor(sums / ONE + 0.5))
    cloud = model.clouds_of(table, sheets)
    assert len(cloud.range_m) == kept.sum() > 10_000
    under_half = (read[:, 0] < model.tau) & kept
    assert under_half.sum() > 0  # cells of p < 1/2 the threshold would never draw


def _copy(tmp_path, draw):
    src = load_model(None).directory
    out = tmp_path / "m"
    shutil.copytree(src, out)
    meta = json.loads((out / "model.json").read_text())
    if draw is None:
        meta.pop("draw")
    else:
        meta["draw"] = draw
    (out / "model.json").write_text(json.dumps(meta))
    return out


def test_a_model_without_a_draw_reads_the_threshold(tmp_path):
    old = load_model(_copy(tmp_path, None))
    assert old.draw == THRESHOLD
    shipped = load_model(None)
    cond = shipped.condition("A320neo", 4500.0, 0.06, pitch=0.03)
    a, b = old.generate(cond).cloud, shipped.generate(cond).cloud
    assert len(a) > 0 and len(b) > 0
    sheets = old.sheets(a_table := old.repeated_conditions(cond, 1))
    s, w, h, read = old.box_reads(a_table, sheets, old.tau)
    assert len(a) == (read[:, 0] > old.tau).sum()


@pytest.mark.parametrize("record, words", [
    ({"rule": "dither"}, "'dither' is not one of threshold, diffuse-rows"),
    ("diffuse-rows", "must be a table with a 'rule'"),
    ({"span": -3}, "must be a table with a 'rule'"),
    ({"rule": "diffuse-rows", "span": float("nan")}, "span must be a logit in -12 .. 0"),
    ({"rule": "diffuse-rows", "span": 1.0}, "span must be a logit in -12 .. 0"),
    ({"rule": "diffuse-rows", "span": True}, "span must be a logit in -12 .. 0"),
    ({"rule": "diffuse-rows", "span": "-3"}, "span must be a logit in -12 .. 0"),
    ({"rule": "diffuse-rows", "spam": -3}, "unknown keys ['spam']"),
    ({"rule": "threshold", "span": -3}, "takes no span"),
])
def test_a_broken_draw_record_is_refused_by_name(tmp_path, record, words):
    with pytest.raises(InputError) as e:
        draw_of(record)
    assert words in str(e.value)
    with pytest.raises(InputError, match="model.json"):
        load_model(_copy(tmp_path, record))


def test_every_registered_draw_round_trips_its_record():
    for name, d in DRAWS.items():
        assert draw_of(d.record()) == d and d.name == name
    assert draw_of({"rule": "diffuse-rows", "span": -5}).span == -5.0


def test_sub_rays_are_drawn_by_the_threshold():
    """The photon stage's K x K sub-rays (sensor/generated.fine_hits) are the thresholded
    model's, whatever the model's own draw (Draw.at_sub_rays); the model keeps its draw."""
    import copy

    from apcg_core.sensor.generated import fine_hits
    model = load_model(None)
    assert model.draw.diffused
    table = np.array([[0, 4000.0, 3.5 * np.pi / 180, 0.05, 0.35, 0.02],
                      [0, 300.0, 3.5 * np.pi / 180, 0.05, 0.1, 0.02]])
    names = ["A320neo", "Mavic 3"]
    got = fine_hits(model, table, names, model.lidar)
    assert model.draw.diffused
    thresholded = copy.copy(model)
    thresholded.draw = THRESHOLD
    want = fine_hits(thresholded, table, names, model.lidar)
    assert len(got.range_m) > 1000
    for f in ("sample", "w", "h", "range_m", "cos"):
        np.testing.assert_array_equal(getattr(got, f), getattr(want, f))
