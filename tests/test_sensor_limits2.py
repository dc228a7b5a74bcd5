"""The photon stage's limits, second round (probe findings 1-6): the per-cloud work check bounds
the signal too, before anything is drawn; ``signal_bins`` adds up in memory that follows its
(sub-ray, bin) terms, with the same bytes on both routes and in the compiled kernel; sensor
names take the catalog's character rule; a file does not pass for a preset it is not; preset
names fold as the catalog's do, lidar and sensor alike. Small synthetic inputs, seconds."""

from __future__ import annotations

import argparse
import dataclasses
import json
import re

import numpy as np
import pytest

from apcg_core.errors import InputError
from apcg_core.lidar import LidarParams, load_lidar
from apcg_core.sensor import (
    PRESET_DIR,
    SubRayHits,
    check_sensor,
    detector,
    load_sensor,
    photon_cloud,
    preset_names,
    stage,
)

DAY = dataclasses.asdict(load_sensor("1550nm-day"))
NIGHT = dataclasses.asdict(load_sensor("1550nm-night"))
SMALL = LidarParams.from_degrees(width=32, height=16)


def _sensor(**over):
    return check_sensor({**NIGHT, "name": "probe", **over})


def _hits(n_cells: int, range_m: float = 3000.0, lidar: LidarParams = SMALL) -> SubRayHits:
    """One sub-ray (K = 1) in each of the first ``n_cells`` cells of one sample's window."""
    cell = np.arange(n_cells)
    return SubRayHits(np.zeros(n_cells, np.int64),
                      (cell % lidar.width + lidar.w_min).astype(np.int32),
                      (cell // lidar.width + lidar.h_min).astype(np.int32),
                      np.full(n_cells, range_m), np.ones(n_cells), 1, 1)


@pytest.fixture
def no_draws(monkeypatch):
    """Any draw of the detector fails the test: a refusal must come before them."""
    def drew(*a, **k):
        raise AssertionError("the detector drew before the cost was checked")
    for name in ("detect", "detect_points", "batch_points"):
        monkeypatch.setattr(stage, name, drew)


# --- finding 1: the signal counts in the per-cloud work check -----------------------------------

@pytest.mark.parametrize("output,dead_ns,pulses", [("events", 0.0, 100), ("points", 0.0, 100),
                                                   ("events", 5.0, 1000)])
def test_a_bright_signal_with_a_short_dead_time_is_refused_before_any_draw(no_draws, output,
                                                                          dead_ns, pulses):
    # ~3e5 photo-electrons a pulse in each of 200 cells: with dead time 0 every arrival is an
    # event; 5 ns (5 bins) still lets 134 a pulse through a gate of 667 bins
    s = _sensor(pulse_energy_j=1e-3, cells_per_pulse=1, dead_time_ns=dead_ns, output=output,
                pulses=pulses)
    assert stage.check_sensor_at(s, SMALL)  # the noise alone fits
    with pytest.raises(InputError) as e:
        photon_cloud(_hits(200), np.array([3000.0]), np.array([1.0]), s, SMALL, 0)
    msg = str(e.value)
    assert "\n" not in msg and "probe" in msg and "at most 2e+07" in msg
    for key in ("pulses", "dead_time_ns", "pulse_energy_j", "gate_m", "background_hz"):
        assert key in msg, msg


def test_many_pulses_of_events_count_their_pulse_numbers(no_draws):
    # 1e5 pulses, one event at most a pulse (dead time > gate), 300 faint lit cells: the
    # noise model alone says 1.6e6, the signal and its (cell, pulse) numbering 6e7
    s = _sensor(pulses=100_000, threshold=3, output="events", dark_count_hz=1e3)
    assert stage.check_sensor_at(s, SMALL)
    with pytest.raises(InputError, match="signal"):
        photon_cloud(_hits(300), np.array([3000.0]), np.array([0.3]), s, SMALL, 0)


def test_a_faint_signal_is_still_drawn_and_the_bound_is_an_upper_bound():
    s = _sensor(output="events", dead_time_ns=0.0)
    rng_work = detector.signal_work(np.array([0.5, 2.0]), np.array([0, 0]), np.array([4.0]),
                                    667, 1e-5, 0.0, 100, False, True)
    # per cell: C events a pulse (dead time 0) + 1 pulse number; plus the 4 terms
    c = np.array([0.5, 2.0]) + 1e-5 * 667
    assert rng_work[0] == pytest.approx(100 * (c + 1).sum() + 4)
    pc = photon_cloud(_hits(20), np.array([3000.0]), np.array([0.6]), s, SMALL, 0)
    assert len(pc.label) > 0 and pc.events


def test_pulse_numbers_are_drawn_a_block_at_a_time_with_the_same_numbers(monkeypatch):
    fired = np.array([3, 0, 7, 10, 1, 5])
    whole = detector._pulse_numbers(np.random.default_rng(9), fired, 10)
    monkeypatch.setattr(detector, "PULSE_NUMBER_CHUNK", 20)  # two cells of 10 pulses a block
    seen = []

    class Spy:
        def __init__(self):
            self.rng = np.random.default_rng(9)

        def random(self, shape):
            seen.append(int(np.prod(shape)))
            return self.rng.random(shape)

    blocks = detector._pulse_numbers(Spy(), fired, 10)
    assert np.array_equal(blocks, whole) and max(seen) <= 20 and len(seen) == 3


def test_the_memory_advice_names_what_drives_the_cost():
    for key in ("pulses", "dead_time_ns", "pulse_energy_j", "gate_m", "background_hz",
                "dark_count_hz"):
        assert key in stage.COST_SETTINGS


# --- finding 2: signal_bins' memory follows its terms, the same bytes ---------------------------

def _guard_bincount(monkeypatch, most: int):
    real = np.bincount

    def bincount(x, weights=None, minlength=0):
        assert minlength <= most, f"a dense array of {minlength} slots"
        return real(x, weights=weights, minlength=minlength)
    monkeypatch.setattr(np, "bincount", bincount)


def test_fine_bins_under_a_sharp_pulse_do_not_allocate_by_bin_span(monkeypatch):
    # 1 um bins, sigma 0: each cell's two sub-rays 1 m apart are 1e6 bins apart; 20 cells
    cell = np.repeat(np.arange(20), 2)
    r = 3000.0 + np.tile([0.0, 1.0], 20) + cell * 1e-3
    first = int(np.floor(2990.0 / 1e-6))
    _guard_bincount(monkeypatch, 10**5)
    sig = stage.signal_bins(cell, r, np.full(40, 0.5), first, 30_000_000, 0.0, 1e-6)
    assert len(sig.cell) == 40 and np.array_equal(sig.cell, cell)
    assert (np.diff(sig.bin)[::2] > 900_000).all() and (sig.mean == 0.5).all()


def _random_terms(seed: int, wide: bool):
    rng = np.random.default_rng(seed)
    n = 400
    cell = np.sort(rng.integers(0, 40, n))
    spread = 2000.0 if wide else 3.0  # bins of 0.01 m across a cell's sub-rays
    r = 100.0 + rng.uniform(0, spread * 0.01, n)
    mean = rng.exponential(1.0, n) * (rng.random(n) > 0.05)
    return cell, r, mean


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("sigma", [0.0, 0.7, 3.2])
def test_the_sorted_and_the_dense_sums_give_the_same_bytes(monkeypatch, seed, sigma):
    cell, r, mean = _random_terms(seed, wide=False)
    dense = stage.signal_bins(cell, r, mean, 9990, 2000, sigma, 0.01)
    monkeypatch.setattr(stage, "DENSE_SLOTS_PER_TERM", 0)
    monkeypatch.setattr(stage, "DENSE_SLOTS_FREE", -1)  # every sum by sorting
    sparse = stage.signal_bins(cell, r, mean, 9990, 2000, sigma, 0.01)
    for f in ("cell", "bin", "mean"):
        a, b = getattr(dense, f), getattr(sparse, f)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), f


@pytest.mark.parametrize("wide", [False, True])
def test_the_compiled_spread_gives_the_numpy_bytes_on_wide_runs_too(wide):
    pytest.importorskip("numba")
    from apcg_core.sensor import kernels
    kernels.require()
    for seed in (4, 5):
        cell, r, mean = _random_terms(seed, wide)
        order = np.random.default_rng(seed).permutation(len(cell))  # unsorted cells too
        for c, rr, m in ((cell, r, mean), (cell[order], r[order], mean[order])):
            a = stage.signal_bins(c, rr, m, 9990, 3000, 1.3, 0.01, compiled=False)
            b = stage.signal_bins(c, rr, m, 9990, 3000, 1.3, 0.01, compiled=True)
            for f in ("cell", "bin", "mean"):
                x, y = getattr(a, f), getattr(b, f)
                assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), f


def test_the_compiled_spread_of_wide_runs_keeps_to_its_terms(monkeypatch):
    pytest.importorskip("numba")
    from apcg_core.sensor import kernels
    k_ = kernels.require()

    class Guarded:
        def __getattr__(self, name):
            if name == "spread_sum":
                raise AssertionError("the kernel's dense slots for runs of 1e6 bins")
            return getattr(k_, name)
    monkeypatch.setattr(kernels, "require", lambda: Guarded())
    cell = np.repeat(np.arange(10), 2)
    r = 3000.0 + np.tile([0.0, 1.0], 10)
    sig = stage.signal_bins(cell, r, np.ones(20), int(2990.0 / 1e-6), 30_000_000, 2.0,
                            1e-6, compiled=True)
    assert len(sig.cell) > 0 and sig.mean.sum() == pytest.approx(20.0, rel=1e-5)


# --- finding 4: sensor names take the catalog's character rule ----------------------------------

@pytest.mark.parametrize("name,words", [("a\nb", "control character"),
                                        ("a\x00b", "control character"),
                                        ("a\u200bb", "invisible"),
                                        ("a\u200fb", "invisible")])
def test_a_sensor_name_with_a_control_or_invisible_character_is_refused(tmp_path, name, words):
    with pytest.raises(InputError, match=words):
        check_sensor({**DAY, "name": name})
    f = tmp_path / "s.toml"
    f.write_text((PRESET_DIR / "1550nm-day.toml").read_text().replace(
        'name = "1550nm-day"', f"name = {json.dumps(name)}"))  # TOML takes JSON's escapes
    with pytest.raises(InputError, match=re.escape(str(f)) + ".*" + words):
        load_sensor(f)


def test_ordinary_sensor_names_stay_accepted():
    for name in ("my day sensor", "Selex-like 1550", "capteur été", ""):
        assert check_sensor({**DAY, "name": name}).name == (name or "custom")


# --- finding 3: a file does not pass for a preset it is not -------------------------------------

def _copy(tmp_path, preset: str, file: str, old: str = "", new: str = ""):
    f = tmp_path / file
    f.write_text((PRESET_DIR / f"{preset}.toml").read_text().replace(old, new))
    return f


def test_a_changed_copy_of_a_preset_under_its_name_is_refused(tmp_path):
    f = _copy(tmp_path, "1550nm-night", "mine.toml", "threshold = 3 ", "threshold = 300 ")
    with pytest.raises(InputError) as e:
        load_sensor(f)
    msg = str(e.value)
    assert "\n" not in msg and "1550nm-night" in msg and "threshold = 300" in msg
    assert "its own name" in msg and "drop name" in msg
    # in another spelling of the preset's name too
    g = _copy(tmp_path, "1550nm-day", "g.toml", 'name = "1550nm-day"', 'name = "1550NM_Day"')
    g.write_text(g.read_text().replace("pulses = 100 ", "pulses = 50 "))
    with pytest.raises(InputError, match="its own name"):
        load_sensor(g)


def test_an_exact_copy_an_own_name_or_no_name_is_accepted(tmp_path):
    assert load_sensor(_copy(tmp_path, "1550nm-night", "a.toml")) == load_sensor("1550nm-night")
    events = _copy(tmp_path, "1550nm-night", "b.toml", 'output = "points"', 'output = "events"')
    assert load_sensor(events).output == "events"  # what it records is not the sensor
    own = _copy(tmp_path, "1550nm-night", "c.toml", 'name = "1550nm-night"', 'name = "mine"')
    own.write_text(own.read_text().replace("threshold = 3 ", "threshold = 5 "))
    assert load_sensor(own).name == "mine"
    stem = _copy(tmp_path, "1550nm-night", "stem.toml", 'name = "1550nm-night"', "")
    stem.write_text(stem.read_text().replace("threshold = 3 ", "threshold = 5 "))
    assert load_sensor(stem).name == "stem"


def test_a_lidar_files_sensor_table_under_a_presets_name_is_held_to_it(tmp_path):
    from apcg_core.lidar_options import lidar_or_default
    f = tmp_path / "l.toml"
    f.write_text("[lidar]\nwidth = 128\n" + (PRESET_DIR / "1550nm-day.toml").read_text()
                 .replace("threshold = 3 ", "threshold = 4 "))
    with pytest.raises(InputError, match="its own name"):
        lidar_or_default(argparse.Namespace(lidar=str(f)))


# --- finding 5: the presets' comments ------------------------------------------------------------

def test_the_night_presets_threshold_comment_is_about_the_dark_counts():
    line = next(ln for ln in (PRESET_DIR / "1550nm-night.toml").read_text().splitlines()
                if ln.startswith("threshold"))
    assert "dark count" in line and "day background" not in line


def test_every_preset_value_cites_its_source():
    for name in preset_names():
        for ln in (PRESET_DIR / f"{name}.toml").read_text().splitlines():
            key = ln.split("=")[0].strip()
            if "=" in ln and not ln.startswith("#") and key not in ("name", "model", "output"):
                assert "#" in ln and ln.split("#", 1)[1].strip(), (name, ln)


# --- finding 6: preset names fold as the catalog's do, one lookup for both kinds -----------------

@pytest.mark.parametrize("spelling", ["1550NM-DAY", "1550nm_day", " 1550nm day ", "1550Nm-Day"])
def test_a_sensor_preset_in_any_spelling(spelling):
    assert load_sensor(spelling) == load_sensor("1550nm-day")


def test_ideal_in_any_spelling_and_the_refusal_lists_the_presets():
    assert load_sensor("IDEAL") is None and load_sensor("Ideal") is None
    with pytest.raises(InputError) as e:
        load_sensor("1550nm-dusk")
    for name in preset_names():
        assert name in str(e.value)


@pytest.mark.parametrize("spelling,name", [("PAPER", "paper"), ("Double_Cells", "double-cells"),
                                           ("half cells", "half-cells")])
def test_a_lidar_preset_in_any_spelling(spelling, name):
    from apcg_core.lidar_options import lidar_or_default
    assert lidar_or_default(argparse.Namespace(lidar=spelling)) == load_lidar(name)


def test_both_kinds_of_preset_go_through_one_lookup():
    from apcg_core.lidar import LIDAR_PRESET_DIR, lidar_file
    from apcg_core.typetable import find_preset
    assert find_preset("HALF_CELLS", LIDAR_PRESET_DIR).stem == "half-cells"
    assert find_preset("1550NM NIGHT", PRESET_DIR).stem == "1550nm-night"
    assert find_preset("./paper", LIDAR_PRESET_DIR) is None  # a path is a file
    assert lidar_file("Half Cells").stem == "half-cells"  # every reader of a lidar reference


def test_a_lidar_preset_in_any_spelling_on_the_command_line(tmp_path, capsys):
    from apcg_core.sensor.options import sensor_of
    args = argparse.Namespace(sensor=None, lidar="DOUBLE_CELLS", photon_output=None)
    assert sensor_of(args) is None  # the preset holds no [sensor] table
