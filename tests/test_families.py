"""The comparison families (issue 8) learn: trained at tiny size under one small budget, each
beats its own untrained network on MMD and JSD against the held-out standard clouds."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from apcg_core.families import load_model as load_any
from training import protocol
from training.data import DepthDataset
from training.export import export_model
from training.trainer import Trainer, config_from


@pytest.fixture
def data(tiny_training_data) -> Path:
    return tiny_training_data


def _means(model, data) -> tuple[float, float]:
    """Mean MMD and JSD over both halves of the tiny held-out split (the protocol's scores)."""
    means = [protocol.score(model, protocol.draw_pairs(data, None, 0, half), floor=False,
                            pointflow=False)["mean"] for half in protocol.HALVES]
    return tuple(float(np.mean([m[k] for m in means])) for k in ("mmd", "jsd"))


# Batches of 8 (and 2 critic steps for the voxel GAN, whose 3D-convolution gradient penalty costs
# 0.45 s a critic step at batch 32 on one thread): 300 steps learn with a clear margin in about a
# minute each, and with lr 0 (training broken) both fail (measured 2026-11-25).
@pytest.mark.parametrize("family,steps,extra", [
    ("point-gan", 300, {"n_critic": 5, "n_points": 64, "batch_size": 8}),
    ("voxel-gan", 300, {"n_critic": 2, "voxel_res": 16, "batch_size": 8}),
    ("diffusion", 600, {"n_points": 64, "diffusion_steps": 50}),
])
def test_family_beats_its_untrained_network(data, tmp_path, family, steps, extra):
    cfg = config_from("tiny", steps=steps, seed=1, family=family, checkpoint_every=10**6,
                      log_every=100, **extra)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    model = load_any(export_model(tmp_path / "run", tmp_path / "m"))
    fresh = protocol.untrained(model, tmp_path / "u")
    trained, untrained = _means(model, data), _means(fresh, data)
    assert trained[0] < untrained[0], (family, "MMD", trained, untrained)
    assert trained[1] < untrained[1], (family, "JSD", trained, untrained)


def test_diffusion_sampling_stays_bounded_when_the_noise_prediction_is_wrong():
    """A denoiser that overshoots (eps = 100 x) fed back into the raw-eps update and overflowed
    to NaN; the update from the clipped x0 keeps every step finite, the result in the clip."""
    import torch

    from apcg_core.nn.baselines import Schedule

    class Overshooting(torch.nn.Module):
        def forward(self, x, t, nu):
            return 100.0 * x

    gen = torch.Generator().manual_seed(0)
    for steps in (None, 20):
        x = Schedule(200).sample(Overshooting(), torch.zeros(4, 8), 32, gen, steps)
        assert torch.isfinite(x).all() and float(x.abs().max()) <= 1.5


def test_generation_refuses_non_finite_points_rather_than_dropping_them(data, tmp_path):
    """Points that are NaN fall in no lidar cell: kept silent, they would shrink (or empty) the
    cloud; generation must stop and name the condition instead."""
    import torch

    cfg = config_from("tiny", steps=1, seed=1, family="point-gan", checkpoint_every=10**6,
                      log_every=100, n_points=32)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    model = load_any(export_model(tmp_path / "run", tmp_path / "m"))
    ds = DepthDataset(data, "test")
    table = ds.condition_rows(np.arange(2))
    assert len(model.generate(table).cloud.xyz) > 0  # the healthy network generates
    with torch.no_grad():
        for p in model.net.parameters():
            p.fill_(float("nan"))
    with pytest.raises(RuntimeError, match="32 non-finite points") as err:
        model.generate(table)
    assert str(np.asarray(table.table[0], float).tolist()) in str(err.value)
    assert "(sample 0)" in str(err.value)


def test_diffusion_sampling_steps_are_chosen_at_export_and_checked(data, tmp_path):
    import json

    from apcg_core.errors import InputError

    cfg = config_from("tiny", steps=2, seed=1, family="diffusion", checkpoint_every=10**6,
                      log_every=100, n_points=32, diffusion_steps=50)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    full = load_any(export_model(tmp_path / "run", tmp_path / "full"))
    fast = load_any(export_model(tmp_path / "run", tmp_path / "fast", sampling_steps=5))
    assert json.loads((tmp_path / "full" / "model.json").read_text())["sampling_steps"] == 50
    assert json.loads((tmp_path / "fast" / "model.json").read_text())["sampling_steps"] == 5
    assert (full.sampling_steps, fast.sampling_steps) == (50, 5)
    table = DepthDataset(data, "test").condition_rows(np.arange(3))
    a, b = fast.generate(table, seed=3).cloud, fast.generate(table, seed=3).cloud
    assert len(a.xyz) > 0 and (a.xyz == b.xyz).all()  # seeded: the same clouds again
    # the 5-step sampler is a different sampler: its clouds differ from the 50-step ones
    c = full.generate(table, seed=3).cloud
    assert len(a.xyz) != len(c.xyz) or not (a.xyz == c.xyz).all()
    for bad in (0, 51, 2.5):
        with pytest.raises(InputError, match=r"sampling_steps must be an integer in 1\.\.50"):
            export_model(tmp_path / "run", tmp_path / "bad", sampling_steps=bad)
    pg = config_from("tiny", steps=1, seed=1, family="point-gan", checkpoint_every=10**6,
                     log_every=100, n_points=32)
    Trainer(data, tmp_path / "pg", pg, progress=False).fit()
    with pytest.raises(InputError, match="the point-gan family does not sample on a "
                                         "schedule"):
        export_model(tmp_path / "pg", tmp_path / "pgm", sampling_steps=5)
    assert not (tmp_path / "bad").exists() and not (tmp_path / "pgm").exists()


def test_apcg_generate_runs_a_comparison_family_model(data, tmp_path, capsys):
    """`apcg generate` finds a family's loader through the `apcg.model_families` entry points
    (the core package never imports training), so a family model is used like the cGAN."""
    import json
    import math

    from apcg_core.cli import main
    from apcg_core.errors import InputError
    from apcg_core.families import load_model
    from apcg_core.io import read_cloud

    cfg = config_from("tiny", steps=1, seed=1, family="point-gan", checkpoint_every=10**6,
                      log_every=100, n_points=32)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    mdir = export_model(tmp_path / "run", tmp_path / "m")
    assert type(load_model(mdir)).__name__ == "BaselineModel"
    ds = DepthDataset(data, "test")
    code, r0, beta0, pitch, yaw, roll = ds.conditions[0]
    pose = ["--type", ds.types.name(code), "--range-m", str(r0), "--count", "2"]
    for name, v in zip(("elevation", "pitch", "yaw", "roll"), (beta0, pitch, yaw, roll),
                       strict=True):
        pose += [f"--{name}-deg", str(math.degrees(v))]
    out = tmp_path / "c.npz"
    assert main(["generate", "--model", str(mdir), *pose, "-o", str(out)]) == 0
    cloud, meta = read_cloud(out)
    assert len(cloud) > 0 and set(cloud.sample.tolist()) == {0, 1}
    assert meta["runtime"] == "torch" and meta["tau"] is None
    capsys.readouterr()
    assert main(["generate", "--model", str(mdir), *pose, "--tau", "-0.5", "-o",
                 str(tmp_path / "t.npz")]) == 2
    assert "--tau is an output threshold" in capsys.readouterr().err
    meta_path = mdir / "model.json"
    meta_path.write_text(json.dumps({**json.loads(meta_path.read_text()), "family": "gizmo"}))
    with pytest.raises(InputError, match="unknown model family 'gizmo'; installed: apcg-plus, "
                                         "apcg-plus-incidence, cgan, diffusion, point-gan, "
                                         "voxel-gan"):
        load_model(mdir)


def test_apcg_train_sizes_a_family_from_the_command_line(data, tmp_path, capsys):
    import json

    from apcg_core.cli import main

    run = tmp_path / "run"
    assert main(["train", "--data", str(data), "-o", str(run), "--preset", "tiny", "--family",
                 "point-gan", "--n-points", "48", "--steps", "1", "--no-progress"]) == 0
    train = json.loads((run / "train_config.json").read_text())["train"]
    assert train["family"] == "point-gan" and train["n_points"] == 48
    model = load_any(export_model(run, tmp_path / "m"))
    assert model.cfg.n_points == 48
    assert model.canonical(model.space.encode(DepthDataset(data, "test").conditions[:2]), 0,
                           [10, 10])[0].shape == (48, 3)
    for argv, message in (
            (["--family", "voxel-gan", "--voxel-res", "24"], "voxel_res must be 4 * 2^k"),
            (["--family", "diffusion", "--diffusion-steps", "0"], "--diffusion-steps 0 not "
                                                                    "accepted: an integer from 1 "
                                                                    "to 10000"),
            (["--n-points", "64"], "--n-points does not apply to the cgan family; it sizes "
                                   "diffusion, point-gan (--family)"),
            (["--family", "point-gan", "--voxel-res", "16"], "--voxel-res does not apply to "
                                                             "the point-gan family; it sizes "
                                                             "voxel-gan")):
        capsys.readouterr()
        assert main(["train", "--data", str(data), "-o", str(tmp_path / "bad"), "--preset",
                     "tiny", "--steps", "1", "--no-progress", *argv]) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "bad").exists()  # refused before anything is written
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:  # --model means a model directory, never a family
        main(["train", "--data", str(data), "-o", str(tmp_path / "bad"), "--model", "point-gan"])
    assert exit_.value.code == 2 and "unrecognized arguments: --model" in capsys.readouterr().err


@pytest.mark.parametrize("change,needle", [
    ({"format_version": 99}, "format_version 99 is not one this apcg reads (1 to 1)"),
    ({"format_version": "1"}, "format_version '1'"),
    ({"format_version": True}, "format_version True"),
    ({"format_version": 0}, "format_version 0"),
    ({"format": "apcg-dataset"}, "format 'apcg-dataset' is not an APCG model's"),
])
def test_a_model_json_of_another_format_or_a_newer_version_is_refused(tmp_path, change, needle):
    import shutil

    from apcg_core.errors import InputError
    from apcg_core.families import default_model_dir, load_model
    from apcg_core.families.registry import MODEL_FORMAT_VERSION
    mdir = tmp_path / "m"
    shutil.copytree(default_model_dir(), mdir)
    meta = json.loads((mdir / "model.json").read_text())
    assert meta["format_version"] == MODEL_FORMAT_VERSION  # the shipped one is read
    meta.update(change)
    (mdir / "model.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match=re.escape(needle)):
        load_model(mdir)
    # a model.json from before "format" and "format_version" were written is a first version
    for key in ("format", "format_version"):
        meta.pop(key)
    (mdir / "model.json").write_text(json.dumps(meta))
    assert load_model(mdir).family == "apcg-plus"


@pytest.mark.parametrize("model,change,needle", [
    ("default", {"quantize": "false"}, "'quantize' must be true or false (a JSON boolean), "
                                       "got 'false'"),
    ("default", {"quantize": 0}, "'quantize' must be true or false"),
    ("default", {"tau": float("nan")}, "must be a finite number, got nan"),
    ("default", {"tau": "0.5"}, "got '0.5'"),
    ("default", {"tau": True}, "tau must be a number, got True"),
    ("default", {"lidar": None}, "it lacks 'lidar'"),
    ("cgan", {"norm": "true"}, "'norm' must be true or false"),
    ("cgan", {"tau": "high"}, "tau must be a number, got 'high'"),
    ("cgan", {"tau": 2.0}, "tau = 2.0 is out of range"),
])
def test_a_model_json_setting_of_the_wrong_kind_is_refused_naming_the_file(tmp_path, model,
                                                                           change, needle):
    import shutil

    import apcg_core
    from apcg_core.errors import InputError
    from apcg_core.families import load_model
    mdir = tmp_path / model
    shutil.copytree(Path(apcg_core.__file__).parent / "models" / model, mdir)
    meta = json.loads((mdir / "model.json").read_text())
    for k, v in change.items():
        if v is None:
            meta.pop(k)
        else:
            meta[k] = v
    (mdir / "model.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match=re.escape(needle)) as refused:
        load_model(mdir)
    assert str(mdir / "model.json") in str(refused.value)


@pytest.mark.parametrize("seed", [None, -1, 1.5, True])
def test_a_comparison_family_seed_is_a_whole_number_at_least_0(data, tmp_path, seed):
    """None drew unseeded noise (a different cloud each call) and -1 a numpy traceback: the
    seed is checked as the cGAN's is, and 2**32 - 1 (the largest block seed) still works."""
    from apcg_core.errors import InputError
    cfg = config_from("tiny", steps=1, seed=1, family="point-gan", checkpoint_every=10**6,
                      log_every=100, n_points=32)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    model = load_any(export_model(tmp_path / "run", tmp_path / "m"))
    table = DepthDataset(data, "test").condition_rows(np.arange(1))
    with pytest.raises(InputError, match="seed must be an integer >= 0"):
        model.generate(table, 1, seed)
    assert len(model.generate(table, 1, np.uint32(2**32 - 1)).table) == 1
