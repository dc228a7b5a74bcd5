"""The model families as the trainer, export and evaluation use them: one object per family,
registered under the ``apcg.model_families`` entry points (pyproject.toml) and found through
:func:`apcg_core.families.get_family`. Everything that differs between families lives here;
nothing else asks which family it holds.

A family object provides:

* ``name``; ``load(directory, runtime)`` -> a model whose ``generate(conditions, count, seed)``
  makes clouds;
* ``train_options()`` -> the family-specific sizes it takes (name -> default);
* ``net_config(train_cfg, dataset)`` -> its network configuration (``to_dict()`` is saved with
  every checkpoint), ``networks(net_config)`` -> (generator or denoiser, critic or None);
* ``prepare(dataset)`` (once, off the training clock); ``batch(trainer, idx)`` -> the real
  batch of samples ``idx``; ``batches_per_step(cfg)``; ``train_step(trainer)`` -> one step's
  log row;
* ``export(state, header, out_dir, meta, data_dir, sampling_steps)`` -> the model directory;
* ``untrained(model, out_dir, seed)`` -> the same network freshly initialised, loaded.
"""

from __future__ import annotations

import json
import shutil
import weakref
from pathlib import Path

import numpy as np

from apcg_core.condition import NOISE_DIM
from apcg_core.errors import InputError

from .baselines.data import CanonicalClouds, CountLookup, voxel_centres
from .baselines.family import FamilyConfig

# torch (and the trainer and networks, which import it) is imported where it is used: opening a
# cGAN model through the registry runs on onnxruntime and must not wait for torch.


class Family:
    """What every family shares: sizes, refusing a sampling-step count, writing its model."""

    name: str
    sizes: tuple[str, ...] = ()  # the family-specific TrainConfig sizes it takes

    def train_options(self) -> dict:
        from .trainer import size_defaults
        defaults = size_defaults()
        return {k: defaults[k] for k in self.sizes}

    def prepare(self, dataset) -> None:
        """Work on the training data done once, before the training clock starts."""

    def check_sampling_steps(self, sampling_steps, state: dict) -> None:
        """Refuses a sampling-step count unless the family samples on a schedule."""
        if sampling_steps is not None:
            raise InputError(f"sampling_steps: the {self.name} family does not sample on a "
                             "schedule, so it takes no sampling-step count")

    def __repr__(self) -> str:
        return f"<model family {self.name}>"


class GANFamily(Family):
    """A generator against a critic, WGAN-GP (or BCE, the ablation's loss), ``n_critic``
    critic batches per generator step; every random draw from the step's own generator."""

    def batches_per_step(self, cfg) -> int:
        return cfg.n_critic

    def train_step(self, tr) -> dict:
        import torch
        import torch.nn.functional as F

        from .trainer import gradient_penalty, step_generator
        cfg = tr.cfg
        wgan = cfg.loss == "wgan-gp"
        b = cfg.batch_size
        tr.G.train()
        tr.D.train()
        for j in range(cfg.n_critic):
            real, nu = tr.next_batch()
            gen = step_generator(cfg.seed, tr.step, j, tr.rank)
            z = torch.randn(b, NOISE_DIM, generator=gen)
            with tr.autocast():
                with torch.no_grad():
                    fake = tr.G(z, nu)
                d_real = tr.D(real, nu).float()
                d_fake = tr.D(fake, nu).float()
            if wgan:
                eps = torch.rand(b, generator=gen)
                gp = gradient_penalty(tr.D, real, fake.float(), nu, eps)
                loss_d = d_fake.mean() - d_real.mean() + cfg.gp_lambda * gp
            else:
                gp = torch.zeros(())
                loss_d = (F.binary_cross_entropy_with_logits(d_real, torch.ones_like(d_real))
                          + F.binary_cross_entropy_with_logits(d_fake, torch.zeros_like(d_fake)))
            tr.opt_d.zero_grad(set_to_none=True)
            loss_d.backward()
            tr.allreduce_grads(tr.D)
            tr.opt_d.step()
        gen = step_generator(cfg.seed, tr.step, cfg.n_critic, tr.rank)
        z = torch.randn(b, NOISE_DIM, generator=gen)
        with tr.autocast():
            score = tr.D(tr.G(z, nu), nu).float()
        loss_g = (-score.mean() if wgan else
                  F.binary_cross_entropy_with_logits(score, torch.ones_like(score)))
        tr.opt_g.zero_grad(set_to_none=True)
        loss_g.backward()
        tr.allreduce_grads(tr.G)
        tr.opt_g.step()
        tr.sync_buffers(tr.G)
        return tr.finish_step(loss_d, loss_g, gp, d_real.mean() - d_fake.mean())


# --- the paper's cGAN ------------------------------------------------------------------------
class CGANFamily(GANFamily):
    """The improved cGAN (SPEC section 7): depth images, exported to ONNX."""

    name = "cgan"

    @staticmethod
    def load(directory, runtime: str = "auto"):
        from apcg_core.generation import APCGModel
        return APCGModel(directory, runtime=runtime)

    def net_config(self, cfg, dataset):
        from apcg_core.nn import NetConfig
        return NetConfig(width=cfg.width, conv=cfg.conv, attention=cfg.attention,
                         loss=cfg.loss, height=dataset.height, width_px=dataset.width)

    def networks(self, net):
        from apcg_core.nn import Discriminator, Generator
        return Generator(net), Discriminator(net)

    def batch(self, tr, idx):
        import torch
        return torch.from_numpy(tr.data.images(idx, normalized=tr.cfg.norm))[:, None]

    def export(self, state: dict, header: dict, out_dir, meta: dict, data_dir,
               sampling_steps=None) -> Path:
        from apcg_core.nn import Generator, NetConfig

        from .export import export_onnx
        self.check_sampling_steps(sampling_steps, state)
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        g = Generator(NetConfig(**state["net"]))
        g.load_state_dict(state["G"])
        export_onnx(g, out / "generator.onnx")
        (out / "model.json").write_text(json.dumps(meta, indent=1) + "\n")
        return out

    def untrained(self, model, out_dir, seed: int = 0):
        """The same network, freshly initialised (seeded), as a model directory; it keeps the
        model's current Im2PC threshold, so both go through the same pipeline."""
        import torch

        from apcg_core.generation import APCGModel
        from apcg_core.nn import Generator, NetConfig

        from .export import export_onnx
        out = Path(out_dir)
        torch.manual_seed(seed)
        out.mkdir(parents=True, exist_ok=True)
        export_onnx(Generator(NetConfig(**model.meta["net"])), out / "generator.onnx")
        (out / "model.json").write_text(json.dumps({**model.meta, "tau": model.tau}))
        return APCGModel(out, runtime="onnx")


# --- the comparison families (the paper's section 3.1) ---------------------------------------
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
    to the lidar's cells at generation (``training.baselines.model.BaselineModel``)."""

    def load(self, directory, runtime: str = "auto"):
        from .baselines.model import BaselineModel  # (every runtime is torch)
        return BaselineModel(directory, family=self)

    def net_config(self, cfg, dataset) -> FamilyConfig:
        return FamilyConfig(self.name, cfg.n_points, cfg.voxel_res, cfg.diffusion_steps)

    def prepare(self, dataset) -> None:
        canonical_clouds(dataset)

    def export(self, state: dict, header: dict, out_dir, meta: dict, data_dir,
               sampling_steps=None) -> Path:
        import torch

        from .data import DepthDataset
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

        from .baselines.model import BaselineModel
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
        from .baselines.nets import PointCritic, PointGenerator
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
        from .baselines.nets import VoxelCritic, VoxelGenerator
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
        from .baselines.nets import Denoiser
        return Denoiser(), None

    def batch(self, tr, idx):
        return _point_sets(tr, idx)

    def batches_per_step(self, cfg) -> int:
        return 1

    def train_step(self, tr) -> dict:
        """One DDPM step: predict the noise added to a batch of canonical point sets."""
        import torch
        import torch.nn.functional as F

        from .trainer import step_generator
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
            from .baselines.nets import check_sampling_steps
            check_sampling_steps(sampling_steps, state["net"]["diffusion_steps"])

    def export_meta(self, state: dict, sampling_steps) -> dict:
        return {"sampling_steps": sampling_steps or state["net"]["diffusion_steps"]}

    def model_sampling_steps(self, model_meta: dict, sampling_steps, net: FamilyConfig):
        if sampling_steps is None:  # the export's choice; None: every step of the schedule
            sampling_steps = model_meta.get("sampling_steps")
        if sampling_steps is not None:
            from .baselines.nets import check_sampling_steps
            check_sampling_steps(sampling_steps, net.diffusion_steps)
        return sampling_steps

    def canonical(self, model, nu: np.ndarray, seed: int, counts) -> list[np.ndarray]:
        import torch
        gen = torch.Generator().manual_seed(int(seed))
        pts = model.cfg.schedule.sample(model.net, torch.from_numpy(nu.astype(np.float32)),
                                        model.cfg.n_points, gen, model.sampling_steps)
        return list(pts.numpy())


CGAN = CGANFamily()
POINT_GAN = PointGANFamily()
VOXEL_GAN = VoxelGANFamily()
DIFFUSION = DiffusionFamily()

__all__ = ["CGAN", "DIFFUSION", "POINT_GAN", "VOXEL_GAN", "BaselineFamily", "Family",
           "GANFamily", "canonical_clouds"]
