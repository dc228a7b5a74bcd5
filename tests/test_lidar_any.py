"""Any SPC-Lidar (issue 33): one lidar description (a preset or a TOML file with the [lidar]
table of the dataset configs, and optionally a [sensor] table) that every command takes as
``--lidar``, models that say where they were measured, and a window that says when it is too
small. Real embree, the real shipped models, small sizes."""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from apcg_core.families import default_model_dir, load_model
from apcg_core.lidar import LIDAR_KEYS, LidarParams, lidar_preset_names, load_lidar
from apcg_core.lidar_options import lidar_of
from tests.cli_run import one_error, run
from tests.output_helpers import commands

DEFAULT_MODEL = default_model_dir()
CGAN_MODEL = DEFAULT_MODEL.parent / "cgan"
POSE = ["--pitch-deg", "3", "--yaw-deg", "20", "--roll-deg", "1"]

# The commands that take a lidar (the list), and every other command that reads a
# model, a sensor or a ray caster, with why it takes none. A new command of that kind fails
# test_every_command_that_meets_a_lidar_takes_lidar until it is in one of the two.
LIDAR_COMMANDS = ("simulate", "generate", "dataset build", "evaluate", "compare", "teach",
                  "figure")
NO_LIDAR = {
    "condition": "prints nu for a model's condition space; no cell is drawn",
    "choose-tau": "chooses tau on the model's own dataset, at the lidar that made it",
    "fd-depth score": "the encoder reads depth images of the dataset's own lidar",
    "export": "writes the run's model; model.json records its training lidar",
}


def lidar_file(tmp: Path, name: str = "mine.toml", **values) -> Path:
    table = {"r_alpha_deg": 0.0060, "r_beta_deg": 0.0100, "r_r_m": 0.3, "width": 192,
             "height": 48, **values}
    body = "".join(f"{k} = {v!r}\n" if not isinstance(v, str) else f"{k} = {v}\n"
                   for k, v in table.items())
    path = tmp / name
    path.write_text("[lidar]\n" + body)
    return path


# --- one option, every command ---------------------------------------------------------------

def test_every_command_that_meets_a_lidar_takes_lidar():
    found = dict(commands())
    for cmd in (*LIDAR_COMMANDS, "scene scan", "scene sequence", "benchmark recognize"):
        assert cmd in found, f"apcg {cmd} is gone"
    for cmd, parser in found.items():
        dests = {a.dest for a in parser._actions}
        meets = cmd in LIDAR_COMMANDS or dests & {"model", "sensor", "backend"}
        if not meets or cmd in NO_LIDAR:
            continue
        lidar = [a for a in parser._actions if a.dest == "lidar"]
        assert lidar, (f"apcg {cmd} reads a model, a sensor or a ray caster but takes no "
                       "--lidar (apcg_core.lidar_options.add_lidar_argument), nor says why "
                       "in NO_LIDAR")
        assert lidar[0].metavar == "PRESET|FILE.toml" and "half-cells" in lidar[0].help, cmd


TAKES_LIDAR = [cmd for cmd, p in commands() if any(a.dest == "lidar" for a in p._actions)]


@pytest.mark.parametrize("cmd", TAKES_LIDAR)
def test_every_lidar_command_reads_the_same_presets_and_files(cmd, tmp_path):
    parser = dict(commands())[cmd]
    mine = lidar_file(tmp_path)
    for ref, want in (("half-cells", load_lidar("half-cells")),
                      (str(mine), LidarParams.from_degrees(0.006, 0.01, 0.3, 192, 48))):
        action = next(a for a in parser._actions if "--lidar" in a.option_strings)
        args = argparse.Namespace()
        action(parser, args, ref, "--lidar")  # what parsing "--lidar REF" does
        assert lidar_of(args) == want, (cmd, ref)


def test_the_paper_is_the_default_and_presets_are_what_they_say():
    assert load_lidar() == LidarParams() == load_lidar("paper")
    assert {"paper", "half-cells", "double-cells", "bin-0.05m", "bin-0.6m",
            "anisotropic"} <= set(lidar_preset_names())
    half, double = load_lidar("half-cells"), load_lidar("double-cells")
    assert half.r_alpha == pytest.approx(LidarParams().r_alpha / 2)
    assert double.r_beta == pytest.approx(LidarParams().r_beta * 2)
    for name in lidar_preset_names():  # every preset keeps the paper's field of view
        lid = load_lidar(name)
        assert lid.width * lid.r_alpha == pytest.approx(256 * LidarParams().r_alpha)
        assert lid.height * lid.r_beta == pytest.approx(64 * LidarParams().r_beta)


BAD_FILES = [
    ("[lidar]\nr_alpha_deg = 0.004\nwidht = 256\n", ["widht", "accepted", "r_alpha_deg"]),
    ("[lidar]\nr_alpha_deg = -1.0\n", ["r_alpha_deg", "-1.0", "> 0"]),
    ("[lidar]\nr_r_m = \"fine\"\n", ["r_r_m", "'fine'"]),
    ("[lidar]\nwidth = 255\n", ["width", "255", "even"]),
    ("[lidar]\nheight = true\n", ["height", "True"]),
    ("[lidar]\nwidth = 65536\nr_alpha_deg = 0.01\n", ["180 deg", "width", "65536",
                                                       "r_alpha_deg", "0.01"]),
    ("[sensor]\nname = \"x\"\n", ["no [lidar] table"]),
    ("[lidar]\n[optics]\nf = 1\n", ["'optics'", "[sensor]"]),
    ("[lidar\nwidth = 4\n", ["not a readable TOML"]),
]


@pytest.mark.parametrize("text,words", BAD_FILES, ids=[w[0] for _, w in BAD_FILES])
def test_a_bad_lidar_file_is_one_line_naming_the_value(tmp_path, capsys, text, words):
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    rc, _, err = run(["simulate", "--type", "Mavic 3", "--range-m", "300", "--elevation-deg",
                      "3.5", *POSE, "--lidar", bad, "-o", tmp_path / "c.npz"], capsys)
    line = one_error(rc, err, *words)
    assert str(bad) in line
    assert not (tmp_path / "c.npz").exists()


def test_an_unknown_preset_names_the_presets(tmp_path, capsys):
    rc, _, err = run(["generate", "--type", "Mavic 3", "--range-m", "300", "--elevation-deg",
                      "3.5", *POSE, "--lidar", "papr", "-o", tmp_path / "g.npz"], capsys)
    one_error(rc, err, "'papr'", "paper", "half-cells")


# --- simulate: the window says when it is too small, and what fits ----------------------------

def test_a_window_too_small_warns_with_the_window_that_fits(tmp_path, capsys):
    argv = ["simulate", "--type", "A380-800", "--range-m", "3000", "--elevation-deg", "3.5",
            "--pitch-deg", "5", "--yaw-deg", "0", "--roll-deg", "5"]
    rc, out, err = run([*argv, "-o", tmp_path / "a.npz"], capsys)
    assert rc == 0, err
    warn = [ln for ln in err.splitlines() if "window too small" in ln]
    assert len(warn) == 1 and "256 x 64" in warn[0] and "A380-800" in warn[0], err
    assert json.loads(out)["clipped"] is True
    w = int(warn[0].split("width = ")[1].split(",")[0])
    h = int(warn[0].split("height = ")[1].split(" ")[0])
    assert w > 256 and h > 64 and w % 2 == 0 == h % 2
    fits = lidar_file(tmp_path, "fits.toml", r_alpha_deg=0.004, r_beta_deg=0.0076, r_r_m=0.15,
                      width=w, height=h)
    rc, out, err = run([*argv, "--lidar", fits, "-o", tmp_path / "b.npz"], capsys)
    assert rc == 0 and "window too small" not in err, err
    held = json.loads(out)["points"]
    assert held > json.loads(run([*argv, "-o", tmp_path / "c.npz"], capsys)[1])["points"]
    wider = lidar_file(tmp_path, "wider.toml", r_alpha_deg=0.004, r_beta_deg=0.0076,
                       r_r_m=0.15, width=w + 40, height=h + 20)
    rc, out, err = run([*argv, "--lidar", wider, "-o", tmp_path / "d.npz"], capsys)
    assert rc == 0 and json.loads(out)["points"] == held, (held, out)  # it was whole
    narrower = lidar_file(tmp_path, "narrower.toml", r_alpha_deg=0.004, r_beta_deg=0.0076,
                          r_r_m=0.15, width=w, height=h - 2)
    rc, _, err = run([*argv, "--lidar", narrower, "-o", tmp_path / "e.npz"], capsys)
    assert rc == 0 and "window too small" in err, err  # and it is the smallest that fits


def test_a_lidar_files_sensor_table_is_the_sensor_unless_one_is_given(tmp_path, capsys):
    from apcg_core.sensor.params import PRESET_DIR
    lid = tmp_path / "spc.toml"
    lid.write_text(lidar_file(tmp_path, "plain.toml").read_text()
                   + (PRESET_DIR / "1550nm-night.toml").read_text())
    argv = ["simulate", "--type", "Mavic 3", "--range-m", "300", "--elevation-deg", "3.5",
            *POSE, "--lidar", lid, "--supersample", "1"]
    rc, out, err = run([*argv, "-o", tmp_path / "p.npz"], capsys)
    assert rc == 0, err
    assert json.loads(out)["sensor"] == "1550nm-night"
    rc, out, err = run([*argv, "--sensor", "ideal", "-o", tmp_path / "q.npz"], capsys)
    assert rc == 0 and "sensor" not in json.loads(out), (out, err)
    with np.load(tmp_path / "p.npz") as z:
        meta = json.loads(str(z["meta"]))
    assert meta["lidar"]["r_r_m"] == 0.3 and meta["sensor"]["name"] == "1550nm-night"


# --- models: which can take another lidar, and where they were measured ------------------------

def test_a_cgan_refuses_another_lidar_in_one_line(tmp_path, capsys):
    rc, _, err = run(["generate", "--model", CGAN_MODEL, "--type", "A320neo", "--range-m",
                      "5000", "--elevation-deg", "3.5", *POSE, "--lidar", "half-cells",
                      "-o", tmp_path / "g.npz"], capsys)
    one_error(rc, err, "cgan", "apcg-plus", "0.002 x 0.0038 deg cells")


def test_generate_warns_once_outside_what_the_model_was_measured_on(tmp_path, capsys):
    argv = ["generate", "--type", "A320neo", "--range-m", "5000", "--elevation-deg", "3.5",
            *POSE]
    mine = tmp_path / "m"  # the shipped model, its record of measured lidars set here
    shutil.copytree(DEFAULT_MODEL, mine)
    meta = json.loads((mine / "model.json").read_text())

    def measured(*names):
        meta["measured_lidars"] = [{"lidar": load_lidar(n).to_dict(), "source": "a test"}
                                   for n in names]
        (mine / "model.json").write_text(json.dumps(meta))

    measured()  # its training lidar alone
    rc, _, err = run([*argv, "--model", mine, "--lidar", "paper", "-o", tmp_path / "a.npz"],
                     capsys)
    assert rc == 0 and "warning" not in err, err
    rc, _, err = run([*argv, "--model", mine, "--lidar", "half-cells", "-o",
                      tmp_path / "b.npz"], capsys)
    warn = [ln for ln in err.splitlines() if "warning:" in ln]
    assert rc == 0 and len(warn) == 1 and "outside what the model" in warn[0], err
    assert "r_alpha_deg 0.002 (measured: 0.004)" in warn[0]
    measured("half-cells")  # measured there: silent there, and the span grows
    rc, _, err = run([*argv, "--model", mine, "--lidar", "double-cells", "-o",
                      tmp_path / "c.npz"], capsys)
    assert rc == 0 and "r_alpha_deg 0.008 (measured: 0.002..0.004)" in err, err
    rc, _, err = run([*argv, "--model", mine, "--lidar", "half-cells", "-o",
                      tmp_path / "d.npz"], capsys)
    assert rc == 0 and "warning" not in err, err
    # the shipped model's record names lidars every --lidar can read
    shipped = load_model()
    assert shipped.measured_lidars()[0] == shipped.trained_lidar == LidarParams()


def test_apcg_plus_reads_its_sheet_at_the_lidars_cells():
    model = load_model()
    cond = model.condition("A320neo", 6000.0, 3.5 * np.pi / 180, 0.05, 0.3, 0.02)
    base = model.generate(cond).cloud
    model.use_lidar(load_lidar("half-cells"))
    fine = model.generate(cond).cloud
    # four times the cells of the same target, give or take its outline
    assert 3.0 < len(fine) / len(base) < 5.0, (len(fine), len(base))
    lid = load_lidar("half-cells")
    assert fine.cell_w.max() < lid.width // 2 and fine.cell_h.max() < lid.height // 2
    assert np.allclose(fine.range_m, lid.quantize_range(fine.range_m))


# --- end to end on a non-default lidar ---------------------------------------------------------

def test_build_simulate_generate_evaluate_on_a_non_default_lidar(tmp_path, capsys):
    lid = lidar_file(tmp_path)  # 0.006 x 0.010 deg cells, 0.3 m bins, 192 x 48
    want = load_lidar(lid)
    cfg = tmp_path / "tiny.toml"
    cfg.write_text('seed = 5\nbackend = "embree"\nshard_size = 50\ntest_fraction = 0.5\n'
                   'sampling = "random"\nsamples_per_type = 8\n'
                   'types = ["Mavic 3", "A320neo"]\n'
                   "[lidar]\nr_r_m = 0.15\n")  # the config's lidar, overridden by --lidar
    rc, _, err = run(["dataset", "build", "--config", cfg, "--lidar", lid, "-o",
                      tmp_path / "ds", "--no-progress"], capsys)
    assert rc == 0, err
    head = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    assert LidarParams.from_dict(head["lidar"]) == want
    rc, out, err = run(["simulate", "--type", "A320neo", "--range-m", "6000",
                        "--elevation-deg", "3.5", *POSE, "--lidar", lid, "-o",
                        tmp_path / "s.npz"], capsys)
    assert rc == 0 and json.loads(out)["points"] > 0, err
    rc, out, err = run(["generate", "--type", "A320neo", "--range-m", "6000",
                        "--elevation-deg", "3.5", *POSE, "--lidar", lid, "-o",
                        tmp_path / "g.npz"], capsys)
    assert rc == 0 and json.loads(out)["points"] > 0, err
    with np.load(tmp_path / "s.npz") as s, np.load(tmp_path / "g.npz") as g:
        for z in (s, g):  # both on the file's bins and cells, and say so
            assert LidarParams.from_dict(json.loads(str(z["meta"]))["lidar"]) == want
            assert np.allclose(z["range_m"], want.quantize_range(z["range_m"]))
            assert np.abs(z["cell_w"]).max() <= want.width // 2
    rc, _, err = run(["evaluate", "--data", tmp_path / "ds", "--lidar", lid, "--pairs", "4",
                      "--no-faithfulness", "-o", tmp_path / "rep"], capsys)
    assert rc == 0, err
    assert "another lidar" not in err  # the model generated at the dataset's lidar
    rep = json.loads((tmp_path / "rep" / "metrics.json").read_text())
    assert LidarParams.from_dict(rep["lidar"]) == want
    # without --lidar the model draws at its own, and says the scores compare two lidars
    rc, _, err = run(["evaluate", "--data", tmp_path / "ds", "--pairs", "4",
                      "--no-faithfulness", "-o", tmp_path / "rep2"], capsys)
    assert rc == 0 and "another lidar" in err, err


def test_lidar_keys_are_the_dataset_configs():
    from dataset_builder.schema import SCHEMA
    assert tuple(SCHEMA["lidar"].keys) == LIDAR_KEYS


# --- photons from the generator: the same stage as simulate, fed the model's sub-rays ----------

def test_the_sub_ray_lidar_centres_are_the_sub_ray_grid():
    from apcg_core.sensor.generated import SUB_READS, sub_ray_lidar
    lid = load_lidar("anisotropic")
    fine = sub_ray_lidar(lid)
    k = SUB_READS
    assert k % 2 == 1
    w = np.arange(-lid.width // 2, lid.width // 2)
    for i in range(k):  # sub-ray i of cell w: (w + (i + 0.5) / k - 0.5) R_alpha
        want = (w + (i + 0.5) / k - 0.5) * lid.r_alpha
        got, _ = fine.cell_centre_angles(k * w + i - (k - 1) // 2, 0, 0.0)
        assert np.allclose(got, want, rtol=0, atol=1e-15)
        assert fine.inside(k * w + i - (k - 1) // 2, 0).all()


@pytest.mark.parametrize("name,range_m", [("Mavic 3", 300.0), ("A320neo", 4000.0)])
def test_generated_photons_see_the_partial_cells_the_simulator_sees(name, range_m):
    """The shipped model's 3 x 3 sub-reads reach the cells a target covers in part, as the
    simulator's sub-rays do (one read per cell misses them: 25-40% fewer cells measured)."""
    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.sensor import load_sensor, photon_cloud, reflectivity_of
    from apcg_core.sensor.generated import hits_of_cloud, sub_ray_hits
    from dataset_builder.simulate import Simulator
    model, cat, sensor = load_model(), default_catalog(), load_sensor("1550nm-night")
    table = np.array([[0, range_m, 3.5 * np.pi / 180, 0.05, 0.35, 0.02]])
    with Simulator("embree", model.lidar, supersample=4) as sim:
        simulated, _, _ = sim.photon_cells_type(cat, name, table, sensor, 1)
    res = model.generate(model.conditions([name], table[:, 1:]))
    rho = np.array([reflectivity_of(cat.get(name))])
    cells = {}
    for how, hits in (("sub", sub_ray_hits(model, res.table, [name], model.lidar)),
                      ("cell", hits_of_cloud(res.cloud, table[:, 2], model.lidar, 1))):
        pc = photon_cloud(hits, table[:, 1], rho, sensor, model.lidar, 1, np.array([0]))
        cells[how] = len(pc.target_w)
    want = len(simulated.target_w)
    assert abs(cells["sub"] - want) < 0.2 * want, (cells, want)
    assert abs(cells["cell"] - want) > 2 * abs(cells["sub"] - want), (cells, want)


def test_teach_simulates_fits_and_scores_at_the_lidar_asked(tmp_path):
    """`apcg teach --lidar`: the new type's dataset is made at that lidar, and the report says
    so (a real process, with a catalog of the user's own holding a type the model lacks)."""
    import os
    import subprocess
    import sys

    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.catalog.importer import export_mesh
    apcg = [sys.executable, "-m", "apcg_core.cli"]
    mesh = tmp_path / "drone.ply"
    export_mesh(default_catalog().mesh("Mavic 3"), mesh)
    env = {**os.environ, "APCG_DATA_DIR": str(tmp_path / "cat")}
    r = subprocess.run([*apcg, "catalog", "add", mesh, "--name", "Lidar Drone", "--kind",
                        "drone"], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    r = subprocess.run([*apcg, "teach", "--model", DEFAULT_MODEL, "--type", "Lidar Drone",
                        "--lidar", "bin-0.6m", "-o", tmp_path / "taught", "--data",
                        tmp_path / "data", "--samples", "8", "--steps", "2"],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr
    want = load_lidar("bin-0.6m")
    head = json.loads((tmp_path / "data" / "dataset.json").read_text())
    assert LidarParams.from_dict(head["lidar"]) == want
    rep = json.loads((tmp_path / "taught" / "teach.json").read_text())
    assert LidarParams.from_dict(rep["lidar"]) == want


def test_every_figure_refuses_the_options_it_does_not_read(tmp_path, capsys):
    """Each figure and each option it does not read (training/cli.py FIGURE_OPTIONS): exit 2,
    one line naming the option, no file; an option was once silently ignored (figure 16
    --run, photons --model)."""
    from training.cli import FIGURE_OPTIONS
    value = {"run": tmp_path, "tau": "0.5", "model": DEFAULT_MODEL, "data": tmp_path,
             "pairs": "3", "lidar": "half-cells", "max_checkpoints": "2"}
    assert set(FIGURE_OPTIONS["all"]) == set(value)
    refused = 0
    for number, takes in FIGURE_OPTIONS.items():
        if number == "all":
            continue
        for option in set(value) - set(takes):
            flag = "--" + option.replace("_", "-")
            rc, _, err = run(["figure", number, flag, value[option], "-o",
                              tmp_path / "f.png"], capsys)
            assert rc == 2, (number, option, err)
            lines = err.strip().splitlines()
            assert len(lines) == 1 and f"does not take {flag}" in lines[0], (number, err)
            refused += 1
    assert refused >= 25 and not (tmp_path / "f.png").exists()
