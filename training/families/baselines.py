"""Training the comparison families (the paper's section 3.1), conditioned on the same nu and
trained on the same standard data with the cGAN's trainer: a voxel GAN (3D-GAN family,
"voxel-gan"), a direct point-cloud GAN (r-GAN family, "point-gan") and a point-cloud diffusion
model (DPM family, "diffusion"). Their runtime is ``apcg_core/families/baselines.py``, their
networks ``apcg_core/nn/baselines.py``."""

from __future__ import annotations

import json
import shutil
import weakref
from pathlib import Path

import numpy as np

from apcg_core.condition import NOISE_DIM
from apcg_core.families.baselines import (
    CountLookup,
    FamilyConfig,
    to_canonical,
    voxel_centres,
    voxel_index,
)

from .base import Family, GANFamily


class CanonicalClouds:
    """The train split's clouds in the canonical frame (kept in memory, a few MB)."""

    def __init__(self, ds) -> None:
        self.ds = ds
        lengths = ds.types.column("depth_length_m").astype(np.float64)
        self.length = lengths[ds.conditions[:, 0].astype(int)]
        self.counts = np.diff(ds.offsets)
        self.clouds = [to_canonical(ds.standard_cloud(i), ds.conditions[i, 1],
                                    ds.conditions[i, 2], self.length[i]).astype(np.float32)
                       for i in range(len(ds))]

    def points(self, idx, n: int, seed: int) -> np.ndarray:
        """(B, n, 3): each cloud resampled to n points (with replacement when it has fewer;
        an empty cloud gives n copies of the centre)."""
        rng = np.random.default_rng(seed)
        out = np.zeros((len(idx), n, 3), np.float32)
        for k, i in enumerate(idx):
            c = self.clouds[int(i)]
            if len(c):
                out[k] = c[rng.choice(len(c), n, replace=len(c) < n)]
        return out

    def voxels(self, idx, res: int) -> np.ndarray:
        """(B, 1, res, res, res) occupancy of each cloud over [-1, 1]^3."""
        out = np.zeros((len(idx), 1, res, res, res), np.float32)
        for k, i in enumerate(idx):
            v = voxel_index(self.clouds[int(i)], res)
            out[k, 0, v[:, 0], v[:, 1], v[:, 2]] = 1.0
        return out


_CLOUDS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def canonical_clouds(dataset) -> CanonicalClouds:
    """The dataset's clouds in the canonical frame, made once per dataset object."""
    if dataset not in _CLOUDS:
        _CLOUDS[dataset] = CanonicalClouds(dataset)
    return _CLOUDS[dataset]


def _point_sets(tr, idx):
    """(B, n_points, 3) canonical point sets, resampled with the batch's own seed."""
    import torch
    return torch.from_numpy(canonical_clouds(tr.data).points(
        idx, tr.cfg.n_points, seed=[tr.cfg.seed, tr.batch_counter]))


class BaselineFamily(Family):
    """A family whose model is a torch network on canonical point sets or voxel grids, snapped
    to the lidar's cells at generation (:class:`apcg_core.families.baselines.BaselineModel`)."""

    def load(self, directory, runtime: str = "auto"):
        from apcg_core.families.baselines import BaselineModel  # (every runtime is torch)
        return BaselineModel(directory, family=self)

    def net_config(self, cfg, dataset) -> FamilyConfig:
        return FamilyConfig(self.name, cfg.n_points, cfg.voxel_res, cfg.diffusion_steps)

    def prepare(self, dataset) -> None:
        canonical_clouds(dataset)

    def export(self, state: dict, header: dict, out_dir, meta: dict, data_dir,
               sampling_steps=None) -> Path:
        import torch

        from ..data import DepthDataset
        self.check_sampling_steps(sampling_steps, state)
        meta = {**meta, **self.export_meta(state, sampling_steps), "family": self.name}
        train = DepthDataset(data_dir, "train")
        counts = CountLookup(train.conditions[:, 0], train.nu, np.diff(train.offsets))
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        torch.save({"G": state["G"], "net": state["net"]}, out / "weights.pt")
        np.savez(out / "counts.npz", codes=counts.codes, nu=counts.nu, counts=counts.counts,
                 k=counts.k)
        (out / "model.json").write_text(json.dumps(meta, indent=1) + "\n")
        return out

    def export_meta(self, state: dict, sampling_steps) -> dict:
        return {}

    def untrained(self, model, out_dir, seed: int = 0):
        """The same network as ``model``, freshly initialised (seeded), as a model directory."""
        import torch

        from apcg_core.families.baselines import BaselineModel
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        torch.manual_seed(seed)
        net, _ = self.networks(model.cfg)
        torch.save({"G": net.state_dict(), "net": model.meta["net"]}, out / "weights.pt")
        for name in ("counts.npz", "model.json"):
            shutil.copy(model.directory / name, out / name)
        return BaselineModel(out, model.sampling_steps, family=self)

    def model_sampling_steps(self, model_meta: dict, sampling_steps, net: FamilyConfig):
        """The sampling-step count a loaded model uses (None: the family has no schedule)."""
        self.check_sampling_steps(sampling_steps, {"net": net.to_dict()})
        return None


class PointGANFamily(BaselineFamily, GANFamily):
    """r-GAN family: an MLP generator of N canonical points against a PointNet critic."""

    name = "point-gan"
    sizes = ("n_points",)

    def networks(self, net: FamilyConfig):
        from apcg_core.nn.baselines import PointCritic, PointGenerator
        return PointGenerator(net.n_points), PointCritic()

    def batch(self, tr, idx):
        return _point_sets(tr, idx)

    def canonical(self, model, nu: np.ndarray, seed: int, counts) -> list[np.ndarray]:
        import torch
        with torch.no_grad():
            gen = torch.Generator().manual_seed(int(seed))
            z = torch.randn(len(nu), NOISE_DIM, generator=gen)
            return list(model.net(z, torch.from_numpy(nu.astype(np.float32))).numpy())


class VoxelGANFamily(BaselineFamily, GANFamily):
    """3D-GAN family: occupancy grids from transposed 3D convolutions against a 3D critic."""

    name = "voxel-gan"
    sizes = ("voxel_res",)

    def networks(self, net: FamilyConfig):
        from apcg_core.nn.baselines import VoxelCritic, VoxelGenerator
        return VoxelGenerator(net.voxel_res), VoxelCritic(net.voxel_res)

    def batch(self, tr, idx):
        import torch
        return torch.from_numpy(canonical_clouds(tr.data).voxels(idx, tr.cfg.voxel_res))

    def canonical(self, model, nu: np.ndarray, seed: int, counts) -> list[np.ndarray]:
        """The ``counts[i]`` most probable voxels of each grid (a threshold at 0.5 leaves a
        young network's sparse grids nearly empty and has no say in how many points the lidar
        would record)."""
        import torch
        with torch.no_grad():
            gen = torch.Generator().manual_seed(int(seed))
            z = torch.randn(len(nu), NOISE_DIM, generator=gen)
            out = model.net(z, torch.from_numpy(nu.astype(np.float32))).numpy()
        centres = voxel_centres(model.cfg.voxel_res)
        return [centres[np.argsort(-p, kind="stable")[:n]]
                for p, n in zip(out.reshape(len(nu), -1), counts, strict=True)]


class DiffusionFamily(BaselineFamily):
    """DPM family: a PointNet denoiser on a DDPM schedule; generation may stride the schedule
    (``sampling_steps``, chosen at export)."""

    name = "diffusion"
    sizes = ("n_points", "diffusion_steps")

    def networks(self, net: FamilyConfig):
        from apcg_core.nn.baselines import Denoiser
        return Denoiser(), None

    def batch(self, tr, idx):
        return _point_sets(tr, idx)

    def batches_per_step(self, cfg) -> int:
        return 1

    def train_step(self, tr) -> dict:
        """One DDPM step: predict the noise added to a batch of canonical point sets."""
        import torch
        import torch.nn.functional as F

        from ..trainer import step_generator
        x0, nu = tr.next_batch()
        schedule = tr.net_config.schedule
        gen = step_generator(tr.cfg.seed, tr.step, 0, tr.rank)
        t = torch.randint(0, schedule.T, (len(x0),), generator=gen)
        eps = torch.randn(x0.shape, generator=gen)
        tr.G.train()
        with tr.autocast():
            pred = tr.G(schedule.noisy(x0, t, eps), t, nu).float()
        loss = F.mse_loss(pred, eps)
        tr.opt_g.zero_grad(set_to_none=True)
        loss.backward()
        tr.allreduce_grads(tr.G)
        tr.opt_g.step()
        return tr.finish_step(0.0, loss, 0.0, 0.0)

    def check_sampling_steps(self, sampling_steps, state: dict) -> None:
        if sampling_steps is not None:
            from apcg_core.nn.baselines import check_sampling_steps
            check_sampling_steps(sampling_steps, state["net"]["diffusion_steps"])

    def export_meta(self, state: dict, sampling_steps) -> dict:
        return {"sampling_steps": sampling_steps or state["net"]["diffusion_steps"]}

    def model_sampling_steps(self, model_meta: dict, sampling_steps, net: FamilyConfig):
        if sampling_steps is None:  # the export's choice; None: every step of the schedule
            sampling_steps = model_meta.get("sampling_steps")
        if sampling_steps is not None:
            from apcg_core.nn.baselines import check_sampling_steps
            check_sampling_steps(sampling_steps, net.diffusion_steps)
        return sampling_steps

    def canonical(self, model, nu: np.ndarray, seed: int, counts) -> list[np.ndarray]:
        import torch
        gen = torch.Generator().manual_seed(int(seed))
        pts = model.cfg.schedule.sample(model.net, torch.from_numpy(nu.astype(np.float32)),
                                        model.cfg.n_points, gen, model.sampling_steps)
        return list(pts.numpy())


POINT_GAN = PointGANFamily()
VOXEL_GAN = VoxelGANFamily()
DIFFUSION = DiffusionFamily()

__all__ = ["DIFFUSION", "POINT_GAN", "VOXEL_GAN", "BaselineFamily", "CanonicalClouds",
           "canonical_clouds"]
