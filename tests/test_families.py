"""The comparison families (issue 8) learn: trained at tiny size under one small budget, each
beats its own untrained network on MMD and JSD against the held-out standard clouds."""

from pathlib import Path

import pytest

from training.baselines.model import load_any
from training.data import DepthDataset
from training.export import export_model
from training.quick_eval import band_mean, evaluate, untrained_like
from training.trainer import Trainer, config_from


@pytest.fixture
def data(tiny_training_data) -> Path:
    return tiny_training_data


def _means(report: dict) -> tuple[float, float]:
    return band_mean(report, "mmd"), band_mean(report, "jsd")


@pytest.mark.parametrize("family,steps,extra", [
    ("point-gan", 300, {"n_critic": 5, "n_points": 64}),
    ("voxel-gan", 300, {"n_critic": 5, "voxel_res": 16}),
    ("diffusion", 600, {"n_points": 64, "diffusion_steps": 50}),
])
def test_family_beats_its_untrained_network(data, tmp_path, family, steps, extra):
    cfg = config_from("tiny", steps=steps, seed=1, family=family, checkpoint_every=10**6,
                      log_every=100, **extra)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    model = load_any(export_model(tmp_path / "run", tmp_path / "m"))
    fresh = untrained_like(model, tmp_path / "u")
    ds = DepthDataset(data, "test")
    trained, untrained = _means(evaluate(model, ds, 200)), _means(evaluate(fresh, ds, 200))
    assert trained[0] < untrained[0], (family, "MMD", trained, untrained)
    assert trained[1] < untrained[1], (family, "JSD", trained, untrained)


def test_diffusion_sampling_stays_bounded_when_the_noise_prediction_is_wrong():
    """A denoiser that overshoots (eps = 100 x) fed back into the raw-eps update and overflowed
    to NaN; the update from the clipped x0 keeps every step finite, the result in the clip."""
    import torch

    from training.baselines.nets import Schedule

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
    import numpy as np
    import torch

    cfg = config_from("tiny", steps=1, seed=1, family="point-gan", checkpoint_every=10**6,
                      log_every=100, n_points=32)
    Trainer(data, tmp_path / "run", cfg, progress=False).fit()
    model = load_any(export_model(tmp_path / "run", tmp_path / "m"))
    ds = DepthDataset(data, "test")
    table = ds.conditions[:2]
    assert len(model.generate(table).cloud.xyz) > 0  # the healthy network generates
    with torch.no_grad():
        for p in model.net.parameters():
            p.fill_(float("nan"))
    with pytest.raises(RuntimeError, match="32 non-finite points") as err:
        model.generate(table)
    assert str(np.asarray(table[0], float).tolist()) in str(err.value)
    assert "(sample 0)" in str(err.value)
