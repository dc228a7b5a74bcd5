"""What a model's user is told where a model and a request do not go together: the way on it
offers (teach only where the family can be taught), a model.json that disagrees with the
model's network or with itself (refused at load, naming the file), the small-data dead ends of
fd-depth and figure 19, and a model trained on a sensor's photon clouds (no second --sensor)."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from apcg_core.errors import InputError
from apcg_core.families import ModelTypes, default_model_dir, load_model
from tests.cli_run import one_error, run

CGAN_DIR = Path(default_model_dir()).parent / "cgan"
POSE = ["--range-m", "4500", "--elevation-deg", "3.4", "--pitch-deg", "2.3"]


def copy_model(src: Path, dst: Path, edit=None) -> Path:
    """A copy of model ``src`` at ``dst``, its model.json changed by ``edit(meta)``."""
    shutil.copytree(src, dst)
    if edit is not None:
        meta = json.loads((dst / "model.json").read_text())
        edit(meta)
        (dst / "model.json").write_text(json.dumps(meta))
    return dst


def drop_type(name: str):
    """An edit that takes type ``name`` out of a model.json consistently (codes renumbered,
    drone_types and n_types following): a model that never knew it."""
    def edit(meta: dict) -> None:
        types = meta["types"]
        gone = next(t["code"] for t in types if t["name"] == name)
        meta["types"] = [{**t, "code": t["code"] - (t["code"] > gone)} for t in types
                         if t["code"] != gone]
        space = meta["condition_space"]
        space["drone_types"] = [c - (c > gone) for c in space.get("drone_types", [])
                                if c != gone]
        space["n_types"] = len(meta["types"])
        if "n_types" in (meta.get("net") or {}):
            meta["net"]["n_types"] = len(meta["types"])
    return edit


# --- 1. teach is offered only where the family can be taught ------------------------------------
def test_a_cgan_lacking_a_type_does_not_offer_teach(tmp_path, capsys):
    model = copy_model(CGAN_DIR, tmp_path / "m", drop_type("Mavic 3"))
    rc, _, err = run(["generate", "--model", model, "--type", "Mavic 3", *POSE,
                      "-o", tmp_path / "g.npz"], capsys)
    line = one_error(rc, err, "'Mavic 3'", "cannot be taught", "apcg train")
    assert "apcg teach --model" not in line, line
    assert not (tmp_path / "g.npz").exists()


@pytest.mark.parametrize("family", ["point-gan", "voxel-gan", "diffusion"])
def test_a_baseline_lacking_a_type_does_not_offer_teach(tmp_path, family):
    def edit(meta):
        drop_type("Mavic 3")(meta)
        meta["family"] = family
    model = ModelTypes(copy_model(CGAN_DIR, tmp_path / "m", edit))  # its model.json alone
    assert not model.can_be_taught()
    with pytest.raises(InputError) as e:
        model.type_name("Mavic 3")
    assert "cannot be taught" in str(e.value) and "apcg teach --model" not in str(e.value)


def test_an_apcg_plus_model_lacking_a_type_still_offers_teach(tmp_path):
    model = ModelTypes(copy_model(default_model_dir(), tmp_path / "m", drop_type("Mavic 3")))
    assert model.can_be_taught()
    with pytest.raises(InputError, match=r"apcg teach --model .* --type 'Mavic 3'"):
        model.type_name("Mavic 3")


def test_figure_16_names_its_fixed_types(tmp_path):
    from training.figures import FIG16_TYPES, fig16
    model = load_model(copy_model(CGAN_DIR, tmp_path / "m", drop_type("Mavic 3")))
    with pytest.raises(InputError) as e:
        fig16(model, tmp_path / "f16.png")
    text = str(e.value)
    assert "figure 16" in text and "'Mavic 3'" in text and "apcg teach" not in text, text
    assert all(t in text for t in FIG16_TYPES), text
    assert not (tmp_path / "f16.png").exists()


# --- 2. a model.json that disagrees with the network or with itself: refused at load -----------
def test_a_cgan_whose_lidar_is_not_its_images_is_refused_at_load(tmp_path, capsys):
    model = copy_model(CGAN_DIR, tmp_path / "m", lambda m: m["lidar"].update(width=512))
    with pytest.raises(InputError) as e:
        load_model(model)
    assert str(model / "model.json") in str(e.value) and "256 x 64" in str(e.value)
    rc, _, err = run(["generate", "--model", model, "--type", "A320neo", *POSE,
                      "-o", tmp_path / "g.npz"], capsys)
    line = one_error(rc, err, str(model / "model.json"), "512 x 64", "disagree")
    assert "im2pc" not in line


@pytest.mark.parametrize("keep,words", [
    (97, "lists 97"),  # the last type cut: every type's nu scaled over 98 codes
    (90, "drone_types [90, 91, 92, 93, 94, 95]"),  # drone codes past the table
])
@pytest.mark.parametrize("src", [CGAN_DIR, default_model_dir()], ids=["cgan", "apcg-plus"])
def test_a_types_table_shorter_than_the_condition_space_is_refused(tmp_path, capsys, keep,
                                                                   words, src):
    def edit(meta):
        meta["types"] = meta["types"][:keep]
        if "n_types" in (meta.get("net") or {}):  # what the network check reads: agree
            meta["net"]["n_types"] = keep
    model = copy_model(src, tmp_path / "m", edit)
    rc, _, err = run(["generate", "--model", model, "--type", "A320neo", *POSE,
                      "-o", tmp_path / "g.npz"], capsys)
    one_error(rc, err, str(model / "model.json"), "n_types 98", words)
    assert not (tmp_path / "g.npz").exists()


# --- 3. small data: fd-depth and figure 19 -----------------------------------------------------
SMALL = """seed = 2
backend = "embree"
sampling = "random"
samples_per_type = 5
test_fraction = 0.2
types = ["A320neo", "F-16C Fighting Falcon"]

[lidar]
r_alpha_deg = 0.016
r_beta_deg = 0.0304
r_r_m = 0.15
width = 64
height = 16
"""


@pytest.fixture(scope="module")
def small_data(tmp_path_factory) -> Path:
    """8 training and 2 held-out samples of two aircraft (no drone), a 64 x 16 window."""
    from dataset_builder.build import build_dataset
    root = tmp_path_factory.mktemp("small")
    (root / "small.toml").write_text(SMALL)
    build_dataset(str(root / "small.toml"), root / "ds", progress=False)
    return root / "ds"


def test_fd_depth_trains_on_fewer_samples_than_a_batch(small_data, tmp_path, capsys):
    from training.fd_depth import train_encoder
    meta = train_encoder(small_data, tmp_path / "enc", epochs=1, progress=False)
    assert meta["batch"] == 8 and (tmp_path / "enc" / "encoder.pt").is_file()
    err = capsys.readouterr().err
    assert "8 samples" in err and "batches of 8" in err, err
    with pytest.raises(InputError, match="fewer than one batch of 16: give a batch of at "
                                         "most 8"):
        train_encoder(small_data, tmp_path / "enc2", epochs=1, batch=16, progress=False)


def test_fd_depth_score_says_which_side_is_short(small_data, tmp_path):
    from training.fd_depth import DepthEncoder, fd_depth, frechet_distance
    enc = DepthEncoder(2, 16, 64)
    with pytest.raises(InputError) as e:  # 1 test pair: refused before anything is generated
        fd_depth(enc, load_model(), small_data, n_pairs=None)
    text = str(e.value)
    assert "at least 4 test pairs" in text and str(small_data) in text, text
    with pytest.raises(InputError, match=r"got 1 \(real images\) and 3 \(generated images\)"):
        frechet_distance(np.zeros((1, 4)), np.zeros((3, 4)),
                         ("real images", "generated images"))


def test_figure_19_on_a_small_dataset_has_no_empty_legend(small_data, tmp_path):
    from training.figures import fig19
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        data = fig19(load_model(), small_data, tmp_path / "f19.png", n_pairs=None)
    assert "drone" not in data  # no drone in the data: its panels are empty
    assert (tmp_path / "f19.png").is_file()
    legend = [str(w.message) for w in caught if "legend" in str(w.message)]
    assert not legend, legend


# --- 4. a model of a sensor's photon clouds -----------------------------------------------------
SENSOR = {"name": "1550nm-day", "wavelength_nm": 1550.0, "output": "points", "pulses": 100}


def test_a_sensor_model_refuses_a_second_sensor(tmp_path, capsys):
    model = copy_model(default_model_dir(), tmp_path / "m", lambda m: m.update(sensor=SENSOR))
    assert load_model(model).sensor == SENSOR
    assert load_model().sensor is None  # a model of standard clouds
    rc, _, err = run(["generate", "--model", model, "--type", "A320neo", *POSE,
                      "--sensor", "1550nm-night", "-o", tmp_path / "g.npz"], capsys)
    one_error(rc, err, "--sensor", "1550nm-day", "already carry", str(model))
    assert not (tmp_path / "g.npz").exists()
    rc, out, err = run(["generate", "--model", model, "--type", "A320neo", *POSE,
                        "-o", tmp_path / "g.npz"], capsys)
    assert rc == 0 and (tmp_path / "g.npz").is_file(), err


def test_the_recognition_benchmark_puts_no_photons_on_a_sensor_models_clouds(tmp_path):
    from apcg_core.sensor import load_sensor
    from training.recognize import Source
    model = copy_model(default_model_dir(), tmp_path / "m", lambda m: m.update(sensor=SENSOR))
    with pytest.raises(InputError, match="already carry"):
        Source(str(model), sensor=load_sensor("1550nm-night"))
    assert Source(str(model)).model.sensor == SENSOR  # without a sensor: its own clouds


def test_a_sensor_record_that_is_no_table_is_refused(tmp_path):
    model = copy_model(default_model_dir(), tmp_path / "m",
                       lambda m: m.update(sensor="1550nm-day"))
    with pytest.raises(InputError, match="model.json: 'sensor' must be the table"):
        load_model(model)
