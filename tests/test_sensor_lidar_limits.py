"""What a sensor or lidar file may ask for: integers TOML can hold, lidar cells and bins that
keep the arithmetic finite, a sensor whose pairing with the lidar can record something and fits
in memory, and warnings that name the sensor when it, not the geometry, empties a cloud. Every
refusal is one line, exit 2, before anything is drawn. Real embree and the real photon stage,
small windows."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from apcg_core.cli import main
from apcg_core.errors import InputError
from apcg_core.io.toml_file import read_toml
from apcg_core.lidar import LidarParams, lidar_preset_names, load_lidar
from apcg_core.sensor import SubRayHits, load_sensor, photon_cloud, preset_names
from apcg_core.sensor.detector import work_per_window
from apcg_core.sensor.link import bin_seconds, noise_per_bin
from apcg_core.sensor.params import MAX_NAME_CHARS, check_sensor
from apcg_core.sensor.stage import MAX_WORK_PER_CLOUD, check_sensor_at
from tests.cli_run import one_error, run

BIG = "1" + "0" * 400  # a TOML integer of 401 digits: tomllib reads it, float() cannot
DAY = dataclasses.asdict(load_sensor("1550nm-day"))
SIM = ["simulate", "--type", "A320neo", "--range-m", "4500", "--elevation-deg", "3.4",
       "--pitch-deg", "2"]


def sensor_file(tmp: Path, name="s.toml", **over) -> Path:
    table = {**DAY, "name": "my-day", **over}  # its own name: a preset's is the preset's
    body = "[sensor]\n" + "".join(
        f"{k} = {v}\n" if isinstance(v, str) and v.isdigit() and len(v) > 30
        else f"{k} = {json.dumps(v)}\n" for k, v in table.items())
    path = tmp / name
    path.write_text(body)
    return path


# --- integers beyond TOML's 64 bits, in every kind of file --------------------------------------
@pytest.mark.parametrize("key", ["gate_m", "pulses", "background_hz", "wavelength_nm"])
def test_a_huge_integer_in_a_sensor_file_is_named(tmp_path, capsys, key):
    path = sensor_file(tmp_path, **{key: BIG})
    one_error(*run([*SIM, "-o", tmp_path / "o.ply", "--sensor", path], capsys)[::2],
              f"sensor.{key}", "64-bit")
    assert not (tmp_path / "o.ply").exists()


@pytest.mark.parametrize("text,key", [
    (f"[lidar]\nr_r_m = {BIG}\n", "lidar.r_r_m"),
    (f"[lidar]\nwidth = -{BIG}\n", "lidar.width"),
    (f"[lidar]\nr_alpha_deg = 0.004\n[sensor]\nmodel = \"ideal\"\npulses = [1, {BIG}]\n",
     "sensor.pulses[1]"),
])
def test_a_huge_integer_in_a_lidar_file_is_named(tmp_path, capsys, text, key):
    path = tmp_path / "l.toml"
    path.write_text(text)
    one_error(*run([*SIM, "-o", tmp_path / "o.ply", "--lidar", path], capsys)[::2],
              key, "64-bit")


def test_a_huge_integer_in_a_dataset_config_and_a_scene_is_named(tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'types = ["A320neo"]\nseed = {BIG}\n')
    one_error(*run(["dataset", "build", "--config", cfg, "-o", tmp_path / "d"], capsys)[::2],
              "seed", "64-bit")
    assert not (tmp_path / "d").exists()
    scene = tmp_path / "sc.toml"
    scene.write_text(f'[[target]]\ntype = "A320neo"\nrange_m = {BIG}\n')
    one_error(*run(["scene", "scan", scene, "-o", tmp_path / "s.npz"], capsys)[::2],
              "target[0].range_m", "64-bit")


def test_toml_reader_keeps_64_bit_integers_and_a_byte_order_mark(tmp_path):
    path = tmp_path / "x.toml"
    path.write_bytes(b"\xef\xbb\xbf" + f"a = {2**63 - 1}\nb = {-(2**63)}\n".encode())
    assert read_toml(path) == {"a": 2**63 - 1, "b": -(2**63)}
    path.write_text(f"a = {2**63}\n")
    with pytest.raises(InputError, match=r"x\.toml: a = 922337203685\.\.\. \(19 digits\)"):
        read_toml(path)
    with pytest.raises(InputError, match="is a directory"):
        read_toml(tmp_path)


# --- lidar cells and bins that keep the arithmetic finite ---------------------------------------
@pytest.mark.parametrize("key,value", [("r_r_m", 1e-320), ("r_r_m", 1e6), ("r_r_m", 1e300),
                                       ("r_alpha_deg", 1e-320), ("r_beta_deg", 1e-12),
                                       ("r_alpha_deg", 11.0)])
def test_lidar_values_outside_their_bounds_are_refused_before_anything_is_cast(
        tmp_path, capsys, key, value):
    path = tmp_path / "l.toml"
    path.write_text(f"[lidar]\n{key} = {value!r}\nwidth = 2\nheight = 2\n")
    line = one_error(*run([*SIM, "-o", tmp_path / "o.ply", "--lidar", path], capsys)[::2],
                     key, "outside")
    assert "inf" not in line.lower().replace("info", "")
    assert not (tmp_path / "o.ply").exists()
    rc, _, err = run(["generate", "--type", "A320neo", "--range-m", "4500",
                      "--elevation-deg", "3.4", "--pitch-deg", "2", "-o", tmp_path / "g.ply",
                      "--lidar", path], capsys)
    one_error(rc, err, key)


def test_every_lidar_preset_lies_inside_the_bounds():
    for name in lidar_preset_names():
        load_lidar(name)  # raises if a preset fell outside
    LidarParams.from_degrees(1e-7, 1e-7, 1e-6)
    LidarParams.from_degrees(10.0, 10.0, 1e3, 2, 2)


# --- a sensor paired with a lidar: something it can record, in memory --------------------------
def test_every_preset_pairs_with_every_lidar_preset():
    for s in preset_names():
        sensor = load_sensor(s)
        if sensor is None:
            continue
        for lidar in lidar_preset_names():
            params = load_lidar(lidar)
            assert check_sensor_at(sensor, params) == math.ceil(sensor.gate_m / params.r_r
                                                                 - 1e-9)


def test_a_threshold_no_pulse_count_can_reach_is_refused_where_it_cannot_be_reached():
    lidar = LidarParams()
    high = check_sensor({**DAY, "threshold": DAY["pulses"] + 1})
    with pytest.raises(InputError, match=r"threshold = 101 is more than pulses = 100"):
        check_sensor_at(high, lidar)
    # a dead time shorter than a bin lets a pulse count several times in one bin
    assert check_sensor_at(dataclasses.replace(high, dead_time_ns=0.0), lidar) > 0
    # the events output has no threshold
    assert check_sensor_at(dataclasses.replace(high, output="events"), lidar) > 0


@pytest.mark.parametrize("over,words", [
    ({"pulse_fwhm_ps": 1e6, "jitter_ps": 1e6}, ["pulse_fwhm_ps", "range bins"]),
    ({"gate_m": 1e5}, ["gate_m = 100000.0", "detector arrivals"]),
    ({"pulses": 100_000}, ["pulses = 100000", "detector arrivals"]),
    ({"dead_time_ns": 0.0, "background_hz": 1e8}, ["background_hz", "detector arrivals"]),
])
def test_a_sensor_too_large_for_memory_is_refused_before_drawing(tmp_path, capsys, over, words):
    path = sensor_file(tmp_path, **over)
    one_error(*run([*SIM, "-o", tmp_path / "o.ply", "--sensor", path], capsys)[::2], *words)
    assert not (tmp_path / "o.ply").exists()
    cfg = tmp_path / "c.toml"
    cfg.write_text('types = ["A320neo"]\n[counts]\nrange_m = 1\nelevation = 1\npitch = 1\n'
                   'yaw = 1\nroll = 1\n')
    rc, _, err = run(["dataset", "build", "--config", cfg, "-o", tmp_path / "d", "--sensor",
                      path], capsys)
    one_error(rc, err, *words)
    assert not (tmp_path / "d").exists()


def test_fine_range_bins_that_spread_a_return_too_wide_name_the_lidar_too():
    with pytest.raises(InputError, match=r"r_r_m = 1e-05.*at most 4096"):
        check_sensor_at(load_sensor("1550nm-day"), LidarParams.from_degrees(r_r_m=1e-5))


@pytest.mark.parametrize("dead_time_ns,gate_m,rate", [(1000.0, 150.0, 3e5), (0.0, 150.0, 3e5),
                                                      (200.0, 3000.0, 2e6)])
def test_the_work_estimate_is_the_mean_number_of_events_drawn(dead_time_ns, gate_m, rate):
    """The budget's estimate against the detector's own draws, noise alone, events output:
    one event a pulse at most (a dead time beyond the gate), Poisson arrivals (no dead time),
    and rate / (1 + rate tau) between."""
    lidar = LidarParams.from_degrees(width=16, height=8)
    s = check_sensor({**DAY, "background_hz": rate, "dark_count_hz": 0.0, "pulses": 200,
                      "output": "events", "gate_m": gate_m, "dead_time_ns": dead_time_ns})
    n_bins = check_sensor_at(s, lidar)
    expected = work_per_window(lidar.width * lidar.height, n_bins, noise_per_bin(s, lidar.r_r),
                               s.dead_time_ns * 1e-9 / bin_seconds(lidar.r_r), s.pulses,
                               s.threshold, False)
    empty = SubRayHits(*(np.zeros(0, t) for t in (np.int64, np.int32, np.int32, float, float)),
                       n_samples=1, sub_rays=1)
    drawn = len(photon_cloud(empty, [9000.0], [1.0], s, lidar, seed=3).label)
    assert drawn == pytest.approx(expected, rel=0.03)


def test_the_budget_admits_what_the_presets_need_at_the_papers_lidar():
    lidar = LidarParams()
    for s in preset_names():
        sensor = load_sensor(s)
        if sensor is not None:
            dead = sensor.dead_time_ns * 1e-9 / bin_seconds(lidar.r_r)
            n_bins = check_sensor_at(sensor, lidar)
            work = work_per_window(lidar.width * lidar.height, n_bins,
                                   noise_per_bin(sensor, lidar.r_r), dead, sensor.pulses,
                                   sensor.threshold, True)
            assert 0 < work < MAX_WORK_PER_CLOUD / 10


# --- messages ------------------------------------------------------------------------------------
@pytest.mark.parametrize("key,value,shown", [("optics_efficiency", 1.0000001, "1.0000001"),
                                             ("pulse_energy_j", 10.000001, "10.000001"),
                                             ("wavelength_nm", 20000.01, "20000.01")])
def test_a_value_just_out_of_range_is_shown_with_all_its_digits(key, value, shown):
    with pytest.raises(InputError) as e:
        check_sensor({**DAY, key: value})
    assert f"= {shown} is out of range" in str(e.value)


def test_a_gate_just_under_two_bins_is_shown_with_all_its_digits():
    s = check_sensor({**DAY, "gate_m": 0.2999999})
    with pytest.raises(InputError, match=r"gate_m = 0\.2999999 m is shorter.*r_r_m = 0\.15 m"):
        check_sensor_at(s, LidarParams())


def test_a_sensor_name_longer_than_a_cloud_file_holds_is_refused(tmp_path, capsys):
    path = sensor_file(tmp_path, name="long.toml")
    path.write_text(path.read_text().replace('name = "my-day"',
                                             f'name = "{"A" * (MAX_NAME_CHARS + 1)}"'))
    one_error(*run([*SIM, "-o", tmp_path / "o.las", "--sensor", path], capsys)[::2],
              "name", f"at most {MAX_NAME_CHARS}")
    ok = sensor_file(tmp_path, name="ok.toml")
    ok.write_text(ok.read_text().replace('name = "my-day"',
                                         f'name = "{"A" * MAX_NAME_CHARS}"'))
    assert run([*SIM, "-o", tmp_path / "o.las", "--sensor", ok], capsys)[0] == 0


def test_a_lidar_files_bad_sensor_table_is_named_even_when_another_sensor_is_used(
        tmp_path, capsys):
    path = tmp_path / "l.toml"
    path.write_text("[lidar]\nwidth = 128\n[sensor]\n" + "".join(
        f"{k} = {json.dumps(-5 if k == 'pulses' else v)}\n" for k, v in DAY.items()))
    for extra in (["--sensor", "ideal"], ["--sensor", "1550nm-day"], []):
        one_error(*run([*SIM, "-o", tmp_path / "o.ply", "--lidar", path, *extra], capsys)[::2],
                  "pulses", "-5")
    one_error(*run(["figure", "photons", "--lidar", path, "-o", tmp_path / "f.png"],
                   capsys)[::2], "pulses")


def test_when_the_sensor_empties_the_cloud_the_warning_says_so(tmp_path, capsys):
    path = sensor_file(tmp_path, visibility_km=0.05)
    rc, out, err = run([*SIM, "-o", tmp_path / "o.ply", "--sensor", path], capsys)
    assert rc == 0, err
    assert "detected little of it" in err and "covers fewer than" not in err
    assert "no cell of the lidar's window sees" not in err


def test_generate_names_the_users_lidar_when_its_sub_rays_do_not_fit(tmp_path, capsys):
    path = tmp_path / "l.toml"
    path.write_text("[lidar]\nwidth = 20\nr_alpha_deg = 8.99\n")  # 179.8 deg across
    rc, _, err = run(["generate", "--type", "A320neo", "--range-m", "4500", "--elevation-deg",
                      "3.4", "--pitch-deg", "2", "-o", tmp_path / "g.ply", "--lidar", path,
                      "--sensor", "1550nm-day"], capsys)
    # one warning (the model was measured on finer cells), then the one error
    line = [ln for ln in err.splitlines() if "error:" in ln]
    assert rc == 2 and len(line) == 1 and "Traceback" not in err, err
    assert "3 x 3 sub-rays" in line[0] and "8.99 x 0.0076 deg cells" in line[0]


def test_generate_takes_a_sensor_at_the_finest_cells_a_lidar_may_have(tmp_path, capsys):
    """1e-7 deg cells are a lidar's finest; a model's 3 x 3 sub-rays of them are finer still,
    which the package's own derived lidar holds (simulate --sensor took this lidar, generate
    refused it naming r_alpha_deg = 3.3e-08)."""
    from apcg_core.lidar import FinerLidar
    from apcg_core.sensor.generated import sub_ray_lidar
    finest = LidarParams.from_degrees(1e-7, 1e-7, 0.15, 64, 16)
    fine = sub_ray_lidar(finest)
    assert isinstance(fine, FinerLidar) and (fine.width, fine.height) == (194, 50)
    assert math.isclose(fine.to_dict()["r_alpha_deg"], 1e-7 / 3, rel_tol=1e-12)
    with pytest.raises(InputError, match="r_alpha_deg"):  # a user's lidar may not be that fine
        LidarParams(fine.r_alpha, fine.r_beta, 0.15, 194, 50)
    path = tmp_path / "l.toml"
    path.write_text("[lidar]\nr_alpha_deg = 1e-7\nr_beta_deg = 1e-7\nwidth = 64\n"
                    "height = 16\n")
    rc, out, err = run(["generate", "--type", "A320neo", "--range-m", "4500",
                        "--elevation-deg", "3.4", "--pitch-deg", "2", "-o",
                        tmp_path / "g.npz", "--lidar", path, "--sensor", "1550nm-night"],
                       capsys)
    assert rc == 0 and "error" not in err, err
    assert json.loads(out.splitlines()[-1])["points"] > 0


def test_a_sensor_file_named_beside_its_dataset_config_is_found_from_anywhere(tmp_path):
    from dataset_builder.plan import load_config
    (tmp_path / "cfg").mkdir()
    sensor_file(tmp_path / "cfg", name="mine.toml")
    cfg = tmp_path / "cfg" / "c.toml"
    cfg.write_text('types = ["A320neo"]\nsensor = "mine.toml"\n')
    here = os.getcwd()
    try:
        os.chdir(tmp_path)
        loaded = load_config(str(cfg))
    finally:
        os.chdir(here)
    assert Path(loaded["sensor"]) == tmp_path / "cfg" / "mine.toml"
    assert load_config(str(cfg.with_name("c.toml")))["sensor"].endswith("mine.toml")


def test_a_bad_sensor_option_is_named_as_the_option(tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text('types = ["A320neo"]\n')
    (tmp_path / "sensors").mkdir()
    rc, _, err = run(["dataset", "build", "--config", cfg, "-o", tmp_path / "d", "--sensor",
                      tmp_path / "sensors"], capsys)
    line = one_error(rc, err, "--sensor", "is a directory")
    assert "dataset config" not in line


def test_simulate_counts_clamped_pixels_without_a_dense_image():
    from apcg_core.depth import pc2im
    rng = np.random.default_rng(0)
    lidar = LidarParams()
    from apcg_core.frames import spherical_to_cartesian
    # points around a target at 6 km, elevation 0.06 rad, some beyond the depth's clamp
    pts = spherical_to_cartesian(rng.normal(0, 0.002, 500), 0.06 + rng.normal(0, 0.0005, 500),
                                 rng.normal(6000, 30, 500))
    img, full = pc2im(pts, 6000.0, 0.06, 20.0, lidar)
    none, stats = pc2im(pts, 6000.0, 0.06, 20.0, lidar, image=False)
    assert none is None and stats == full and full.n_clamped > 0 and img.shape == (64, 256)


def test_photons_figure_counts_covered_cells_of_a_wide_window(tmp_path):
    """Cells 500 or more columns from the centre (an A320neo at 3 km at 0.0005 deg cells) were
    counted under another cell's key; the covered cells are the distinct cells hit."""
    from dataset_builder.simulate import Simulator
    from training.figures import PHOTON_TYPES, fig_photons  # noqa: F401
    lidar = LidarParams.from_degrees(0.0005, 0.0019, 0.15, 1400, 32)
    data = fig_photons(tmp_path / "f.png", types=("A320neo",), sensors=("1550nm-night",),
                       poses=1, seed=2, lidar=lidar)
    assert data["lidar"] == lidar.to_dict()
    from apcg_core.catalog.catalog import default_catalog
    cat = default_catalog()
    t = cat.get("A320neo")
    rng = np.random.default_rng(2)  # the figure's own draws, in its order
    deg = np.pi / 180
    ranges = np.linspace(3000, 18000, 6)
    n = len(ranges)
    tab = np.stack([np.full(n, t.index), ranges, rng.uniform(3, 4, n) * deg,
                    rng.uniform(1, 5, n) * deg, rng.uniform(-60, 60, n) * deg,
                    rng.uniform(-5, 5, n) * deg], 1)
    with Simulator("embree", lidar, supersample=4) as sim:
        hits = sim.sub_ray_hits(cat.mesh(t), tab, ("type", t.index))
    cells = {(int(s), int(w), int(h)) for s, w, h in zip(hits.sample, hits.w, hits.h,
                                                          strict=True)}
    assert max(abs(int(w)) for w in hits.w) >= 500
    want = [sum(1 for c in cells if c[0] == i) for i in range(n)]
    assert data["curves"][0]["covered_cells"] == want


def test_running_out_of_memory_is_one_line_not_a_traceback(capsys):
    def register(sub):
        p = sub.add_parser("probe")
        p.set_defaults(func=lambda args: np.empty(2**62, np.uint8))
    assert main(["probe"], registrars=[register]) == 1
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("apcg probe: error: out of memory")
    assert "Traceback" not in err


def test_window_advice_never_names_a_window_no_lidar_file_may_hold(tmp_path, capsys):
    path = tmp_path / "l.toml"
    path.write_text("[lidar]\nr_alpha_deg = 1e-6\nr_beta_deg = 1e-6\n")
    rc, _, err = run([*SIM, "-o", tmp_path / "o.ply", "--force", "--lidar", path], capsys)
    assert rc == 0, err
    assert "no window at these cells holds it whole" in err and "width =" not in err
    path.write_text("[lidar]\nwidth = 64\n")  # too narrow for an A320neo at 4.5 km
    rc, _, err = run([*SIM, "-o", tmp_path / "o.ply", "--force", "--lidar", path], capsys)
    assert rc == 0 and "a window of width = " in err, err
    width = int(err.split("a window of width = ")[1].split(",")[0])
    path.write_text(f"[lidar]\nwidth = {width}\n")
    rc, _, err = run([*SIM, "-o", tmp_path / "o.ply", "--force", "--lidar", path], capsys)
    assert rc == 0 and "window too small" not in err, err
