"""Data in and out at their edges (a probe's findings, stop 53): a LAS file's meta past one
record's 65,535 bytes, metrics on coordinates whose squares overflow, a model without noise
asked for copies or a seed, configs and CSVs that name what is wrong with them, a dataset
outside a model's conditions. Real commands, real model, small sizes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from apcg_core.cloud import PointCloud
from apcg_core.errors import InputError
from apcg_core.io.clouds import LAS_VLR_BYTES, read_cloud, write_cloud
from apcg_core.metrics import jsd, mmd
from tests.cli_run import one_error, run

HEAD = "type,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg\n"


def _cloud(n=50) -> PointCloud:
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(n, 3)) + [0.0, 0.0, 4500.0]
    return PointCloud(xyz, np.linalg.norm(xyz, axis=1), np.arange(n), np.arange(n),
                      np.zeros(n, np.int64))


@pytest.mark.parametrize("ext", ["las", "laz"])
def test_a_las_meta_past_one_record_is_kept_whole(tmp_path, ext):
    meta = {"conditions": [{"type": f"type {i}", "range_m": 4500.0 + i} for i in range(4000)]}
    assert len(json.dumps(meta)) > 2 * LAS_VLR_BYTES  # three records
    write_cloud(tmp_path / f"c.{ext}", _cloud(), meta)
    cloud, back = read_cloud(tmp_path / f"c.{ext}")
    assert back["conditions"] == meta["conditions"] and len(cloud) == 50


def test_generate_writes_las_for_any_number_of_conditions(tmp_path, capsys):
    rows = [f"A320neo,{4000 + i},3.5,2,{-50 + 0.2 * i:.1f},0" for i in range(450)]
    (tmp_path / "c.csv").write_text(HEAD + "\n".join(rows) + "\n")
    rc, out, err = run(["generate", "--conditions", tmp_path / "c.csv", "-o",
                        tmp_path / "g.las"], capsys)
    assert rc == 0, err
    cloud, meta = read_cloud(tmp_path / "g.las")
    assert len(meta["conditions"]) == 450 and meta["conditions"][449]["range_m"] == 4449.0
    npz, _ = read_cloud(_npz_of(tmp_path, capsys))
    assert np.array_equal(cloud.sample, npz.sample) and np.abs(cloud.xyz - npz.xyz).max() < 1e-4


def _npz_of(tmp_path, capsys):
    rc, _, err = run(["generate", "--conditions", tmp_path / "c.csv", "-o",
                      tmp_path / "g.npz"], capsys)
    assert rc == 0, err
    return tmp_path / "g.npz"


def test_metrics_refuse_coordinates_whose_squares_overflow():
    a = np.random.default_rng(1).random((40, 3))
    assert mmd(a * 1e11, (a + 5) * 1e11) > 0  # far, still scored
    with pytest.raises(InputError, match="coordinate of .* m; accepted: coordinates within"):
        mmd(a * 1e160, (a + 5) * 1e160)  # it said 0.0, a perfect score
    with pytest.raises(InputError, match="bins must be an integer >= 1, got True"):
        jsd(a, a, bins=True)
    with pytest.raises(InputError, match="max_points must be an integer >= 1, got 0"):
        mmd(a, a, max_points=0)


def test_copies_and_a_seed_of_a_model_without_noise_are_warned_about(tmp_path, capsys):
    (tmp_path / "c.csv").write_text(HEAD + "A320neo,4500,3.4,2,10,0\n")
    base = ["generate", "--conditions", tmp_path / "c.csv"]
    rc, _, err = run([*base, "--count", "3", "--seed", "5", "-o", tmp_path / "a.npz"], capsys)
    assert rc == 0
    assert "--count 3 writes 3 identical copies" in err and "--seed 5 changes nothing" in err
    with np.load(tmp_path / "a.npz") as z:  # what the warning says
        s = z["sample"]
        assert np.array_equal(z["xyz"][s == 0], z["xyz"][s == 2])
    rc, _, err = run([*base, "-o", tmp_path / "b.npz"], capsys)
    assert rc == 0 and "warning" not in err, err
    rc, _, err = run([*base, "--count", "3", "--seed", "5", "--sensor", "1550nm-day", "-o",
                      tmp_path / "c.npz"], capsys)
    assert rc == 0 and "identical" not in err and "changes nothing" not in err, err


@pytest.mark.parametrize("types, says", [
    ('["A320neo", "a320NEO"]', "types names one type more than once: 'A320neo', 'a320NEO' "
                               "are all 'A320neo'"),
    ('["A320neo", "A320-neoX"]', "types: unknown aircraft type 'A320-neoX'"),
])
def test_a_configs_types_are_refused_naming_the_config(tmp_path, capsys, types, says):
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'types = {types}\nsampling = "random"\nsamples_per_type = 5\n')
    rc, _, err = run(["dataset", "build", "--config", cfg, "-o", tmp_path / "d"], capsys)
    one_error(rc, err, str(cfg), says)
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("sep, name", [(";", "semicolons"), ("\t", "tabs")])
def test_a_csv_of_another_separator_is_named(tmp_path, capsys, sep, name):
    (tmp_path / "c.csv").write_text(HEAD.replace(",", sep) + sep.join(
        ["A320neo", "4500", "3,4" if sep == ";" else "3.4", "2", "10", "0"]) + "\n")
    rc, _, err = run(["generate", "--conditions", tmp_path / "c.csv", "-o",
                      tmp_path / "g.npz"], capsys)
    one_error(rc, err, "line 1: the header is separated by " + name, "separated by commas")
    assert not (tmp_path / "g.npz").exists()


def test_evaluate_names_the_dataset_and_sample_a_model_does_not_cover(tmp_path, capsys):
    cfg = tmp_path / "far.toml"
    cfg.write_text('types = ["Mavic 3"]\nsampling = "random"\nsamples_per_type = 6\n'
                   'test_fraction = 0.5\n[ranges]\ndrone_range_m = [3000, 3100]\n')
    rc, _, err = run(["dataset", "build", "--config", cfg, "-o", tmp_path / "far",
                      "--no-progress"], capsys)
    assert rc == 0, err
    rc, _, err = run(["evaluate", "--data", tmp_path / "far", "-o", tmp_path / "ev"], capsys)
    line = one_error(rc, err, f"dataset {tmp_path / 'far'}, sample ",
                     "range_m = 30", "is not made for this dataset's conditions")
    assert "row 0" not in line


def test_a_file_where_a_jobs_parts_go_is_named_and_kept(tmp_path, capsys):
    (tmp_path / "c.csv").write_text(HEAD + "A320neo,4500,3.4,2,10,0\n")
    (tmp_path / "g.npz.parts").write_text("mine")
    rc, _, err = run(["generate", "--conditions", tmp_path / "c.csv", "--resumable", "-o",
                      tmp_path / "g.npz"], capsys)
    one_error(rc, err, "g.npz.parts is a file", "move that file away")
    assert (tmp_path / "g.npz.parts").read_text() == "mine" and not (tmp_path / "g.npz").exists()


@pytest.mark.parametrize("closed", ["stdout", "stderr"])
def test_a_reader_that_goes_away_loses_no_output(tmp_path, closed):
    """`apcg ... | head -1`, `2>/dev/null | true`: the pipe's reader is gone before the command
    prints its summary; the command still ends whole, its file kept (it exited 0 without it)."""
    import subprocess
    import sys
    out = tmp_path / "c.npz"
    proc = subprocess.Popen([sys.executable, "-m", "apcg_core.cli", "simulate", "--type",
                             "A320neo", "--range-m", "5000", "--elevation-deg", "3.5", "-o",
                             str(out)],
                            stdout=subprocess.PIPE if closed == "stdout" else subprocess.DEVNULL,
                            stderr=subprocess.PIPE if closed == "stderr" else subprocess.DEVNULL)
    getattr(proc, closed).close()  # the reader goes away at once
    assert proc.wait(timeout=300) == 0
    cloud, _ = read_cloud(out)
    assert len(cloud) > 100


def test_a_value_just_past_a_bound_is_shown_apart_from_it(tmp_path, capsys):
    rc, _, err = run(["simulate", "--type", "A320neo", "--range-m", "3000", "--elevation-deg",
                      "3.5", "--roll-deg=180.00001", "-o", tmp_path / "x.npz"], capsys)
    # the option is refused by its rule, the condition's own range (tests/test_options.py)
    one_error(rc, err, "--roll-deg 180.00001 not accepted", "from -180 to 180")
    # and the condition itself, as a Python caller or a file reaches it
    from apcg_core.condition import Condition
    with pytest.raises(InputError, match=r"roll = 180\.00001 deg is out of range.*"
                                         r"\[-180 deg, 180 deg\]"):
        Condition.from_degrees(0, 3000.0, 3.5, roll_deg=180.00001)
