"""The photon stage where users meet it: `apcg simulate --sensor` and `apcg dataset build` with
a [sensor] (real embree, real processes, a real Dask cluster). The ideal lidar stays
byte-identical; photon builds are byte-identical across workers, engines and resumes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("embreex")

from apcg_core.cli import main  # noqa: E402
from apcg_core.io.dataset import Shard, read_header  # noqa: E402

POSE = ["--type", "A320neo", "--range-m", "4500", "--elevation-deg", "3.4", "--pitch-deg",
        "2.3", "--yaw-deg", "13.2", "--roll-deg", "0.13"]
CONFIG = """seed = 11
shard_size = 6
types = ["A320neo", "F-16C Fighting Falcon", "Mavic 3"]
sampling = "random"
samples_per_type = 12
sensor = "{sensor}"
"""


def simulate(tmp_path, name, *extra):
    out = tmp_path / name
    assert main(["simulate", *POSE, "-o", str(out), *extra]) == 0
    return out


def test_sensor_ideal_gives_the_bytes_of_no_sensor(tmp_path):
    for ext in ("npz", "ply", "las"):
        plain = simulate(tmp_path, f"plain.{ext}")
        ideal = simulate(tmp_path, f"ideal.{ext}", "--sensor", "ideal", "--seed", "5")
        assert plain.read_bytes() == ideal.read_bytes(), ext


def test_photon_cloud_files_carry_labels_and_counts(tmp_path):
    a = simulate(tmp_path, "a.npz", "--sensor", "1550nm-day", "--seed", "3")
    b = simulate(tmp_path, "b.npz", "--sensor", "1550nm-day", "--seed", "3")
    c = simulate(tmp_path, "c.npz", "--sensor", "1550nm-day", "--seed", "4")
    assert a.read_bytes() == b.read_bytes() and a.read_bytes() != c.read_bytes()
    z = np.load(a)
    meta = json.loads(str(z["meta"]))
    assert meta["sensor"]["name"] == "1550nm-day" and meta["seed"] == 3
    assert meta["supersample"] == 4  # a sensor's default: every sub-ray contributes
    assert set(np.unique(z["label"])) <= {0, 1} and (z["count"] >= 3).all()
    assert len(z["label"]) == len(z["xyz"]) > 20
    from apcg_core.io.clouds import read_cloud_attributes
    ply = simulate(tmp_path, "a.ply", "--sensor", "1550nm-day", "--seed", "3")
    _, _, cols = read_cloud_attributes(ply)
    assert np.array_equal(cols["label"], z["label"]) and np.array_equal(cols["count"],
                                                                         z["count"])
    laspy = pytest.importorskip("laspy")
    from apcg_core.sensor import PRESET_DIR
    noisy = tmp_path / "noisy.toml"  # the day preset at threshold 2: noise points for sure
    noisy.write_text((PRESET_DIR / "1550nm-day.toml").read_text().replace(
        "threshold = 3", "threshold = 2").replace('"1550nm-day"', '"noisy"'))
    las_path = simulate(tmp_path, "a.las", "--sensor", str(noisy), "--seed", "3")
    las = laspy.read(las_path)
    npz = simulate(tmp_path, "d.npz", "--sensor", str(noisy), "--seed", "3")
    label = np.load(npz)["label"]
    assert (label == 0).any() and (label == 1).any()
    assert np.array_equal(np.asarray(las.classification), np.where(label == 1, 1, 7))
    assert np.array_equal(np.asarray(las["count"]), np.load(npz)["count"])


def test_events_output_has_pulses_and_several_events_per_cell(tmp_path):
    ev = simulate(tmp_path, "e.npz", "--sensor", "1064nm-night", "--photon-output", "events")
    z = np.load(ev)
    assert "pulse" in z.files and (z["pulse"] >= 0).all() and (z["pulse"] < 100).all()
    cells = z["cell_w"].astype(np.int64) * 1000 + z["cell_h"]
    assert np.bincount(np.unique(cells, return_inverse=True)[1]).max() > 1


@pytest.mark.parametrize("extra, says", [
    (["--sensor", "nope"], "unknown sensor 'nope'"),
    (["--sensor", "1550nm-day", "--backend", "points"], "--sensor needs a ray-casting backend"),
    (["--photon-output", "events"], "--photon-output needs a --sensor"),
    (["--sensor", "1550nm-day", "--no-quantize"], "--no-quantize does not apply with --sensor"),
])
def test_sensor_mistakes_are_one_line(tmp_path, capsys, extra, says):
    rc = main(["simulate", *POSE, "-o", str(tmp_path / "x.npz"), *extra])
    err = capsys.readouterr().err
    assert rc == 2 and says in err and "Traceback" not in err
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.parametrize("option", ["--sensor", "--lidar"])
def test_a_directory_given_for_a_sensor_or_lidar_file_is_called_one(tmp_path, capsys, option):
    folder = tmp_path / "presets"
    folder.mkdir()
    rc = main(["simulate", *POSE, option, str(folder), "-o", str(tmp_path / "x.npz")])
    err = capsys.readouterr().err
    assert rc == 2 and f"'{folder}' is a directory" in err and "Traceback" not in err
    assert not (tmp_path / "x.npz").exists()


def test_a_bad_sensor_table_in_a_config_is_named_before_anything_is_written(tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text('types = ["A320neo"]\n[sensor]\npulses = 3\n')
    rc = main(["dataset", "build", "--config", str(cfg), "-o", str(tmp_path / "ds")])
    err = capsys.readouterr().err
    assert rc == 2 and "lacks" in err and str(cfg) in err
    assert not (tmp_path / "ds").exists()


def _files(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def _build(cfg: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "apcg_core.cli", "dataset", "build", "--config",
                           str(cfg), "-o", str(out), "--no-progress", *extra],
                          capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def photon_config(tmp_path_factory) -> Path:
    cfg = tmp_path_factory.mktemp("cfg") / "photons.toml"
    cfg.write_text(CONFIG.format(sensor="1550nm-day"))
    return cfg


@pytest.fixture(scope="module")
def photon_reference(photon_config, tmp_path_factory) -> dict[str, bytes]:
    out = tmp_path_factory.mktemp("ref") / "ds"
    r = _build(photon_config, out)
    assert r.returncode == 0, r.stderr
    return _files(out)


def test_photon_dataset_holds_labels_counts_and_the_expected_signal(photon_reference,
                                                                   photon_config, tmp_path):
    out = tmp_path / "ds"
    assert _build(photon_config, out).returncode == 0
    head = read_header(out)
    assert head["sensor"]["name"] == "1550nm-day" and head["supersample"] == 4
    assert head["reflectivity"]["F-16C Fighting Falcon"] == 0.15
    n_points = n_targets = 0
    for f in sorted((out / "shards").glob("*.npz")):
        s = Shard.load(f)
        assert len(s.label) == len(s.count) == len(s.pixel)
        assert (s.count >= 3).all() and s.pulse is None
        assert (s.target_signal_pe > 0).all() and s.target_offsets[-1] == len(s.target_pixel)
        n_points += len(s.pixel)
        n_targets += len(s.target_pixel)
    assert n_points > 100 and n_targets > n_points
    # info names the sensor and splits the points; verify re-plans from the recorded sensor
    info = json.loads(subprocess.run([sys.executable, "-m", "apcg_core.cli", "dataset", "info",
                                      str(out), "--verify", "--json"], capture_output=True,
                                     text=True, check=True).stdout)
    assert info["sensor"] == "1550nm-day" and info["verified"]
    assert info["signal_points"] + info["noise_points"] == info["points"] == n_points


@pytest.mark.parametrize("how", [["--workers", "2"], ["--sensor", "1550nm-day"]],
                         ids=["local-pool", "sensor-option"])
def test_photon_builds_are_the_same_bytes_whoever_builds_them(photon_reference, photon_config,
                                                              tmp_path, how):
    out = tmp_path / "ds"
    r = _build(photon_config, out, *how)
    assert r.returncode == 0, r.stderr
    got = _files(out)
    if "--sensor" in how:  # the option names the same sensor: the same shards
        got = {k: v for k, v in got.items() if k.startswith("shards/")}
        want = {k: v for k, v in photon_reference.items() if k.startswith("shards/")}
        assert got == want
    else:
        assert got == photon_reference


def test_photon_build_on_a_dask_cluster_and_resumed_is_the_same_bytes(photon_reference,
                                                                       photon_config, tmp_path):
    pytest.importorskip("distributed")
    out = tmp_path / "ds"
    r = _build(photon_config, out, "--engine", "dask", "--workers", "2")
    assert r.returncode == 0, r.stderr
    assert _files(out) == photon_reference
    # a resumed build: two shards and the manifest lost, the same command again
    shards = sorted((out / "shards").glob("*.npz"))
    for p in (shards[0], shards[-1], out / "manifest.json"):
        p.unlink()
    r = _build(photon_config, out)
    assert r.returncode == 0 and json.loads(r.stdout)["built_shards"] == 2
    assert _files(out) == photon_reference


def test_an_ideal_sensor_config_builds_the_ideal_dataset(tmp_path):
    cfg = tmp_path / "ideal.toml"
    cfg.write_text(CONFIG.format(sensor="ideal"))
    plain = tmp_path / "plain.toml"
    plain.write_text("\n".join(line for line in CONFIG.splitlines()
                               if not line.startswith("sensor")) + "\n")
    assert _build(cfg, tmp_path / "a").returncode == 0
    assert _build(plain, tmp_path / "b").returncode == 0
    a = {k: v for k, v in _files(tmp_path / "a").items() if k.startswith("shards/")}
    b = {k: v for k, v in _files(tmp_path / "b").items() if k.startswith("shards/")}
    assert a == b and len(a) == 9


def test_ctrl_c_in_a_photon_build_then_the_same_command_ends_the_same_bytes(
        photon_reference, photon_config, tmp_path, hold):
    from test_build_engine import _ctrl_c_at
    out = tmp_path / "ds"
    cmd = [sys.executable, "-m", "apcg_core.cli", "dataset", "build", "--config",
           str(photon_config), "-o", str(out), "--no-progress"]
    rc, err = _ctrl_c_at(cmd, hold, "build.shard-written")
    assert rc == 130 and "Traceback" not in err, err
    assert 1 <= len(list((out / "shards").glob("*.npz"))) < 9
    assert not (out / "manifest.json").exists()
    r = _build(photon_config, out)
    assert r.returncode == 0, r.stderr
    assert _files(out) == photon_reference


@pytest.mark.parametrize("output", ["points", "events"])
def test_the_photon_stage_in_chunks_gives_the_same_cells(monkeypatch, output):
    """A batch is cut into chunks of bounded memory; a sample's photons must not notice."""
    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.sensor import load_sensor
    from dataset_builder import simulate
    cat = default_catalog()
    t = cat.get("F-16C Fighting Falcon")
    deg = np.pi / 180
    rng = np.random.default_rng(5)
    table = np.stack([np.full(7, t.index), rng.uniform(3000, 9000, 7), np.full(7, 3.5 * deg),
                      np.full(7, 2 * deg), rng.uniform(-1, 1, 7), np.zeros(7)], 1)
    sensor = load_sensor("1550nm-day").with_output(output)
    with simulate.Simulator(supersample=4) as sim:
        whole, clipped, rays = sim.photon_cells_type(cat, t, table, sensor, 3)
        monkeypatch.setattr(simulate, "PHOTON_RAYS", 1000)  # a chunk per sample
        parts, clipped2, rays2 = sim.photon_cells_type(cat, t, table, sensor, 3)
        empty, _, _ = sim.photon_cells_type(cat, t, table[:0], sensor, 3)
    for f in ("sample", "w", "h", "range_m", "label", "count", "pulse", "target_sample",
              "target_signal_pe"):
        assert np.array_equal(getattr(whole, f), getattr(parts, f)), f
    assert np.array_equal(clipped, clipped2) and np.array_equal(rays, rays2)
    assert len(np.unique(whole.sample)) >= 4 and len(empty.sample) == 0


def test_catalog_add_takes_a_reflectivity_and_the_photons_follow_it(tmp_path, monkeypatch):
    """`catalog add --reflectivity` stores the type's own value; a photon scan of it gets more
    signal from a whiter copy; a bad value is named."""
    from apcg_core.catalog import catalog as catalog_module
    from apcg_core.catalog.catalog import Catalog
    from apcg_core.catalog.mesh import Mesh
    from apcg_core.sensor import reflectivity_of
    from dataset_builder.simulate import Simulator
    src = default_mesh_file(tmp_path)
    env = {**os.environ, "APCG_DATA_DIR": str(tmp_path / "data")}

    def add(name, rho):
        return subprocess.run([sys.executable, "-m", "apcg_core.cli", "catalog", "add",
                               str(src), "--name", name, "--reflectivity", rho],
                              capture_output=True, text=True, env=env, timeout=300)
    for name, rho in (("Dark Jet", "0.05"), ("White Jet", "0.9")):
        r = add(name, rho)
        assert r.returncode == 0, r.stderr
    r = add("Bad Jet", "1.5")
    assert r.returncode == 2 and "--reflectivity" in r.stderr and "Traceback" not in r.stderr
    monkeypatch.setenv("APCG_DATA_DIR", str(tmp_path / "data"))
    cat = Catalog(user_path=catalog_module.user_dir())
    dark, white = cat.get("Dark Jet"), cat.get("White Jet")
    assert reflectivity_of(dark) == 0.05 and reflectivity_of(white) == 0.9
    assert isinstance(cat.mesh(dark), Mesh)
    from apcg_core.sensor import load_sensor
    deg = np.pi / 180
    row = [[0, 9000.0, 3.5 * deg, 2 * deg, 10 * deg, 0.0]]
    signal = {}
    with Simulator(supersample=4) as sim:
        for t in (dark, white):
            cells, _, _ = sim.photon_cells_type(cat, t, np.array(row), load_sensor(
                "1550nm-night").with_output("events"), 1)
            signal[t.name] = int(cells.label.sum())
    assert signal["White Jet"] > 3 * signal["Dark Jet"]


def default_mesh_file(tmp_path: Path) -> Path:
    """The catalog's own A320neo written as a PLY (what a user would import)."""
    out = tmp_path / "jet.ply"
    assert main(["catalog", "export", "A320neo", "-o", str(out)]) == 0
    return out


def test_generate_with_a_sensor(tmp_path):
    """`apcg generate --sensor`: ideal gives the bytes of no sensor; a sensor labels the
    generated clouds' points, seeded by --seed."""
    pose = POSE[2:]
    out = {}
    for name, extra in (("plain", []), ("ideal", ["--sensor", "ideal"]),
                        ("a", ["--sensor", "1550nm-night", "--count", "2"]),
                        ("b", ["--sensor", "1550nm-night", "--count", "2"]),
                        ("c", ["--sensor", "1550nm-night", "--count", "2", "--seed", "9"])):
        out[name] = tmp_path / f"{name}.npz"
        assert main(["generate", "--type", "A320neo", *pose, "-o", str(out[name]),
                     *extra]) == 0
    assert out["plain"].read_bytes() == out["ideal"].read_bytes()
    a, b, c = (np.load(out[k]) for k in "abc")
    assert np.array_equal(a["range_m"], b["range_m"]) and np.array_equal(a["label"], b["label"])
    assert not (len(a["range_m"]) == len(c["range_m"])
                and np.array_equal(a["range_m"], c["range_m"]))
    assert set(np.unique(a["sample"])) <= {0, 1} and (a["count"] >= 3).all()
    plain = np.load(out["plain"])
    assert 0 < len(a["label"]) < 2 * len(plain["xyz"])  # 1550 nm at 4.5 km: some cells only
