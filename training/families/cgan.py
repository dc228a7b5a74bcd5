"""Training the paper's cGAN (SPEC section 7): depth images from the dataset, the WGAN-GP step
shared with the comparison GANs, export to ONNX. Its runtime is ``apcg_core/families/cgan.py``,
its networks ``apcg_core/nn/cgan.py``."""

from __future__ import annotations

import json
from pathlib import Path

from apcg_core.families.cgan import FAMILY

from .base import GANFamily


class CGANFamily(GANFamily):
    """The improved cGAN (SPEC section 7): depth images, exported to ONNX."""

    name = FAMILY
    switches = ("conv", "attention", "loss", "norm", "n_critic")

    @staticmethod
    def load(directory, runtime: str = "auto"):
        from apcg_core.families.cgan import APCGModel
        return APCGModel(directory, runtime=runtime)

    def net_config(self, cfg, dataset):
        from apcg_core.nn.cgan import NetConfig
        return NetConfig(width=cfg.width, conv=cfg.conv, attention=cfg.attention,
                         loss=cfg.loss, height=dataset.height, width_px=dataset.width)

    def networks(self, net):
        from apcg_core.nn.cgan import Discriminator, Generator
        return Generator(net), Discriminator(net)

    def batch(self, tr, idx):
        import torch
        return torch.from_numpy(tr.data.images(idx, normalized=tr.cfg.norm))[:, None]

    def export(self, state: dict, header: dict, out_dir, meta: dict, data_dir,
               sampling_steps=None) -> Path:
        from apcg_core.nn.cgan import Generator, NetConfig

        from ..export import export_onnx
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

        from apcg_core.families.cgan import APCGModel
        from apcg_core.nn.cgan import Generator, NetConfig

        from ..export import export_onnx
        out = Path(out_dir)
        torch.manual_seed(seed)
        out.mkdir(parents=True, exist_ok=True)
        export_onnx(Generator(NetConfig(**model.meta["net"])), out / "generator.onnx")
        (out / "model.json").write_text(json.dumps({**model.meta, "tau": model.tau}))
        return APCGModel(out, runtime="onnx")


CGAN = CGANFamily()

__all__ = ["CGAN", "CGANFamily"]
