"""The photon stage's compiled loops (apcg_core/sensor/kernels.py) against the numpy code they
replace: the same photon clouds, byte for byte, on real embree hits of several catalog types
(far aircraft with a weak signal, near drones whose strong signal takes the chain of
binomials), with every preset (1064 / 1550 nm, day / night), points and events outputs, a
large pulse count (the binomial sampler's start above 0, its lgamma terms) and threshold 1."""

from __future__ import annotations

import dataclasses
import itertools
import os
import re

import numpy as np
import pytest

pytest.importorskip("embreex")
pytest.importorskip("numba")

from apcg_core.catalog.catalog import Catalog  # noqa: E402
from apcg_core.depth import DEFAULT_LIDAR  # noqa: E402
from apcg_core.sensor import (  # noqa: E402
    draws,
    kernels,
    load_sensor,
    photon_cloud,
    points,  # noqa: E402
    reflectivity_of,
)
from apcg_core.sensor.points import BRIGHT_COUNTS, _loud_peaks  # noqa: E402
from dataset_builder.simulate import Simulator  # noqa: E402

CATALOG = Catalog(include_user=False)
DEG = np.pi / 180
TYPES = ["A320neo", "F-16C Fighting Falcon", "Matrice 300 RTK", "Mavic 3"]
FIELDS = ("sample", "w", "h", "range_m", "label", "count", "pulse", "target_sample",
          "target_w", "target_h", "target_signal_pe")


@pytest.fixture(scope="module")
def hits():
    """Sub-ray hits (K = 4) of five Table 1 conditions per type, as bench/photons.py draws
    them, and one type batch of a close drone that fills much of the window."""
    rng = np.random.default_rng(32)
    sim = Simulator("embree", supersample=4)
    out = {}
    for name in TYPES:
        t = CATALOG.get(name)
        lo, hi = (100.0, 600.0) if t.range_band == "near" else (3000.0, 18000.0)
        n = 5
        table = np.stack([np.full(n, t.index), rng.uniform(lo, hi, n),
                          rng.uniform(3, 4, n) * DEG, rng.uniform(1, 5, n) * DEG,
                          rng.uniform(-60, 60, n) * DEG, rng.uniform(-5, 5, n) * DEG], 1)
        if t.range_band == "near":
            table[0, 1] = 60.0
        h = sim.sub_ray_hits(CATALOG.mesh(t), table, ("type", t.index))
        out[name] = (h, table[:, 1].copy(), np.full(n, reflectivity_of(t)))
    return out


def _cloud(monkeypatch, mode, h, r0, rho, sensor, seed=7):
    monkeypatch.setenv(kernels.ENV, mode)
    assert kernels.use_for(1) == (mode == "compiled")
    return photon_cloud(h, r0, rho, sensor, DEFAULT_LIDAR, seed=seed,
                        sample_ids=np.arange(len(r0)) + 1000)


def _same(a, b, what):
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), (what, f)


def test_the_kernels_are_there():
    # CI installs the sim extra, numba included: the comparisons below must not be numpy
    # against numpy.
    os.environ.pop(kernels.ENV, None)
    assert kernels.enabled()
    kernels.require()
    assert kernels.loaded() and kernels.use_for(1)


@pytest.mark.parametrize("preset", ["1550nm-day", "1550nm-night", "1064nm-day",
                                    "1064nm-night"])
def test_both_paths_give_the_same_points_on_every_preset(monkeypatch, hits, preset):
    sensor = load_sensor(preset)
    n_points = n_signal = 0
    for name, (h, r0, rho) in hits.items():
        want = _cloud(monkeypatch, "numpy", h, r0, rho, sensor)
        got = _cloud(monkeypatch, "compiled", h, r0, rho, sensor)
        _same(got, want, (preset, name))
        n_points += len(want.range_m)
        n_signal += int((want.label == 1).sum())
    # not a comparison of empty clouds (noise points, rare at these thresholds: below)
    assert n_points > 1000 and n_signal > 500


@pytest.mark.filterwarnings("error")  # e.g. no 0 / 0 where a piece has nothing after it
@pytest.mark.parametrize("change", [{"output": "events"}, {"pulses": 400},
                                    {"threshold": 1}, {"pulses": 7, "threshold": 2},
                                    {"background_hz": 0.0, "dark_count_hz": 0.0}])
def test_both_paths_give_the_same_bytes_with_other_settings(monkeypatch, hits, change):
    labels = []
    for preset in ("1550nm-day", "1064nm-night"):
        sensor = dataclasses.replace(load_sensor(preset), **change)
        for name, (h, r0, rho) in hits.items():
            if change.get("output") == "events" and name != "Mavic 3":
                h = _first_samples(h, 2)
                r0, rho = r0[:2], rho[:2]
            want = _cloud(monkeypatch, "numpy", h, r0, rho, sensor)
            got = _cloud(monkeypatch, "compiled", h, r0, rho, sensor)
            _same(got, want, (preset, name, change))
            labels.append(want.label)
    labels = np.concatenate(labels)
    assert (labels == 1).sum() > 100
    if change.get("threshold") == 1 or "output" in change:  # noise points too
        assert (labels == 0).sum() > 10


def _first_samples(h, n):
    keep = h.sample < n
    return dataclasses.replace(h, sample=h.sample[keep], w=h.w[keep], h=h.h[keep],
                               range_m=h.range_m[keep], cos=h.cos[keep], n_samples=n)


def test_the_comparisons_reach_every_route_of_the_loud_cells(monkeypatch, hits):
    # Both routes of the fired pulses (by draws, the chain), stretches placed and skipped,
    # faint signal bins in them that events land in, and with 400 pulses chain binomials that
    # start above 0: what the tests above compare is what the kernels do.
    from apcg_core.sensor.link import noise_per_bin, range_sigma_m, signal_photoelectrons
    from apcg_core.sensor.params import check_gate
    from apcg_core.sensor.stage import gate_first_bin, signal_bins

    lidar = DEFAULT_LIDAR
    n_cells = lidar.width * lidar.height
    seen = {"draws": 0, "chain": 0, "big_start": 0, "faint_pieces": 0, "faint_events": 0}
    walk = kernels.require().chain_prepare
    for (_name, (h, r0, rho)), pulses in itertools.product(hits.items(), (7, 100, 400)):
        sensor = dataclasses.replace(load_sensor("1550nm-day"), pulses=pulses)
        n_bins = check_gate(sensor, lidar.r_r)
        pe = signal_photoelectrons(h.range_m, h.cos, rho[h.sample], sensor, h.sub_rays)
        cell = (h.sample.astype(np.int64) * n_cells
                + (h.h.astype(np.int64) - lidar.h_min) * lidar.width
                + (h.w.astype(np.int64) - lidar.w_min))
        first = gate_first_bin(r0, sensor, lidar)
        sig = signal_bins(cell, h.range_m, pe, first[h.sample], n_bins,
                          range_sigma_m(sensor) / lidar.r_r, lidar.r_r)
        noise = noise_per_bin(sensor, lidar.r_r)
        k = kernels.require()
        _, _, p_sig, p_flo, p_fhi, p_mean, _, _, _, before, heads, counts, total = k.pieces(
            sig.cell, sig.bin, sig.mean, n_bins, noise, n_cells, BRIGHT_COUNTS / pulses)
        seen["faint_pieces"] += int((p_fhi > p_flo).sum())
        fired = draws.binomial_inverse(np.full(len(heads), sensor.pulses), -np.expm1(-total),
                                       draws.uniforms(7, np.zeros(len(heads), np.int64),
                                                      draws.FIRED, np.arange(len(heads))))
        chain = fired >= counts
        seen["draws"] += int((~chain).sum())
        seen["chain"] += int(chain.sum())
        # the chain's binomial at the cell's first bright bin: Binomial(left, p), left the
        # pulses the noise before it left (nearly all: margin 30), p the bin's share of the
        # rest of the gate; its start is above 0 when mean - 12 sd is
        at = np.minimum(heads + (p_sig[heads] < 0), len(p_sig) - 1)
        chain &= p_sig[at] >= 0  # a cell with a bright bin
        p = -np.expm1(-p_mean[at]) / -np.expm1(-(total - before[at]))
        q = np.minimum(p, 1 - p)
        mean = fired * q
        with np.errstate(invalid="ignore"):  # cells without a bright bin: not counted
            start = np.floor(mean - 12 * np.sqrt(mean * (1 - q)))
        seen["big_start"] += int((chain & (mean >= 16) & (start > 30)).sum())
        calls = []

        def spy(*args, _placed=points._stretch_bins, _calls=calls):
            out = _placed(*args)
            _calls.append(out[1])
            return out

        monkeypatch.setattr(points, "_stretch_bins", spy)
        _loud_peaks(sig, n_bins, noise, sensor.pulses, sensor.threshold, 7,
                    np.arange(len(r0)), n_cells, compiled=False)
        _loud_peaks(sig, n_bins, noise, sensor.pulses, sensor.threshold, 7,
                    np.arange(len(r0)), n_cells, compiled=True)
        seen["faint_events"] += sum(int((f >= 0).sum()) for f in calls)
    assert walk.signatures
    assert seen["draws"] > 100 and seen["chain"] > 100 and seen["big_start"] > 0
    # stretches holding faint signal bins, and events placed in those bins
    assert seen["faint_pieces"] > 100 and seen["faint_events"] > 10, seen


@pytest.mark.parametrize("n, p", [(5, 0.3), (100, 0.97), (2000, 0.5), (10**6, 0.01),
                                  (40, 0.0), (40, 1.0)])
def test_the_compiled_walk_draws_the_numpy_samplers_bytes(n, p):
    u = draws.uniforms(3, np.zeros(50_000, np.int64), 99, np.arange(50_000))
    nn = np.random.default_rng(0).integers(0, n + 1, 50_000)
    pp = np.full(50_000, p)
    want = draws.binomial_inverse(nn, pp, u)
    got = draws.binomial_inverse(nn, pp, u, compiled=True)
    assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
    if 0 < p < 1 and n > 5:
        assert len(np.unique(got)) > 3  # the walk moved


def test_the_compiled_uniforms_are_the_numpy_hash():
    ids = np.array([0, 5, 2**40, 2**62 + 3], np.int64)
    sample = np.repeat(np.arange(4), 1000)
    index = np.tile(np.arange(1000), 4) * 7919
    for seed, stream in ((0, 1), (2**63 + 11, draws.STRETCH), (123456789, draws.LABELS)):
        got = kernels.require().uniforms(draws.stream_key(seed, stream), ids, sample, index)
        want = draws.uniforms(seed, ids[sample], stream, index)
        assert got.tobytes() == want.tobytes()


def test_the_kernels_hold_no_fused_multiply_add(monkeypatch, hits):
    # An FMA rounds once where the numpy code rounds twice: the kernels must not hold one.
    # Compile them again with their own options but without the cache, for the argument
    # types they were called with, and read the machine code.
    from numba import njit
    h, r0, rho = hits["Mavic 3"]
    for change in ({}, {"pulses": 7, "threshold": 2}):  # with few pulses, the "by draws" route
        sensor = dataclasses.replace(load_sensor("1550nm-day"), **change)
        _cloud(monkeypatch, "compiled", h, r0, rho, sensor)
    draws.binomial_inverse(np.array([10]), np.array([0.3]), np.array([0.5]), compiled=True)
    k = kernels.require()
    fused = re.compile(r"\b(v?fn?m(add|sub)\w*|fml[as]\w*)\b", re.IGNORECASE)
    code = {}
    for name in ("spread_sum", "pieces", "stretch_events", "stretch_peaks", "binomial_walk",
                 "place_fired", "chain_prepare", "chain_finish", "uniforms", "masked_uniforms",
                 "top", "histogram_top", "merge_top"):
        f = getattr(k, name)
        assert f.signatures, name
        options = {o: v for o, v in f.targetoptions.items() if o != "nopython"}
        again = njit(**options)(f.py_func)
        for sig in f.signatures:
            again.compile(sig)
        code[name] = "\n".join(again.inspect_asm().values())
    for name, asm in code.items():
        assert not fused.search(asm), (name, fused.search(asm).group(0))
    assert re.search(r"\b(v?mul[sp][sd]|fmul)\b", code["spread_sum"])  # the pattern reads it


def _signal(h, r0, rho, sensor, compiled, order=None):
    from apcg_core.sensor.link import range_sigma_m, signal_photoelectrons
    from apcg_core.sensor.params import check_gate
    from apcg_core.sensor.stage import gate_first_bin, signal_bins

    lidar = DEFAULT_LIDAR
    n_cells = lidar.width * lidar.height
    pe = signal_photoelectrons(h.range_m, h.cos, rho[h.sample], sensor, h.sub_rays)
    cell = (h.sample.astype(np.int64) * n_cells
            + (h.h.astype(np.int64) - lidar.h_min) * lidar.width
            + (h.w.astype(np.int64) - lidar.w_min))
    first = gate_first_bin(r0, sensor, lidar)[h.sample]
    rng = h.range_m
    if order is not None:
        cell, rng, pe, first = cell[order], rng[order], pe[order], first[order]
    n_bins = check_gate(sensor, lidar.r_r)
    return signal_bins(cell, rng, pe, first, n_bins, range_sigma_m(sensor) / lidar.r_r,
                       lidar.r_r, compiled), n_bins, n_cells


def test_the_signal_and_the_pieces_are_the_same_floats(hits):
    # The float64 sums themselves, not only the integers drawn from them: the spread of every
    # return, added up per (cell, bin) (hits in the simulator's order and shuffled), and each
    # loud cell's pieces with their means and the sums before them.
    from apcg_core.sensor.link import noise_per_bin
    from apcg_core.sensor.points import _pieces

    k = kernels.require()
    for preset in ("1550nm-day", "1064nm-night"):
        sensor = load_sensor(preset)
        noise = noise_per_bin(sensor, DEFAULT_LIDAR.r_r)
        for name, (h, r0, rho) in hits.items():
            shuffle = np.random.default_rng(1).permutation(len(h.range_m))
            for order in (None, shuffle):
                want, n_bins, n_cells = _signal(h, r0, rho, sensor, False, order)
                got, _, _ = _signal(h, r0, rho, sensor, True, order)
                for f in ("cell", "bin", "mean"):
                    a, b = getattr(got, f), getattr(want, f)
                    assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), (name, f)
            # every bin a piece, the split the stage uses, every bin faint (one stretch a cell)
            for bright_min in (0.0, BRIGHT_COUNTS / sensor.pulses, np.inf):
                args = (want.cell, want.bin, want.mean, n_bins, noise, n_cells, bright_min)
                for a, b in zip(k.pieces(*args), _pieces(*args), strict=True):
                    assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), (name, bright_min)
