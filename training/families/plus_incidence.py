"""Training an APCG+ model's incidence output (`apcg train --family apcg-plus-incidence --init
MODEL`): what the photon stage reads instead of the range's slope (SPEC section 8).

A model's sheet is smooth where the standard cloud jumps from one surface to another (a wing
before the fuselage), so the slope of its range reads grazing incidence there, and the photon
stage dims cells the simulator lights (docs/evaluation/lidars, section 2). The incidence
network is a second network of the model's own shape, its weights the start (`--init`), whose
one-channel sheet is the logit of each return's cosine of incidence; it is fitted to the
``cos_incidence`` of an ideal dataset built with ``incidence = true`` (docs/DATASET.md) at the
cells that hold a return, by L1 on the cosine. The model's own network and tau are untouched:
`apcg export` writes the model again, with ``incidence.onnx`` beside its ``sheets.onnx``, this
run's config and log as ``incidence_train_config.json`` and ``incidence_log.csv``, and what
was trained under ``incidence`` in model.json. Log columns: ``loss_d`` and ``loss_g`` are the
L1 of the cosine, ``wasserstein`` the share of returns whose cosine is within 0.1.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from apcg_core.errors import InputError

from .apcg_plus import FAMILY as MODEL_FAMILY
from .apcg_plus import PlusFamily, draw_queries, export_sheets_onnx, without_incidence

NAME = "apcg-plus-incidence"
CLOSE = 0.1  # a cosine "within" this of the data's counts as right in the log


class IncidenceFamily(PlusFamily):
    """An APCG+ model's incidence network, trained from the model (``--init`` is required)."""

    name = NAME
    sizes = ("sheet", "head")
    record_prefix = "incidence_"  # the run's config and log beside the model's own
    # a fine-tune of the model's own network (its rate for fine-tuning, plus/README)
    train_defaults = {**PlusFamily.train_defaults, "lr": 1e-4}

    @staticmethod
    def load(directory, runtime: str = "auto"):
        raise InputError(f"{directory}: {NAME} is how an {MODEL_FAMILY} model's incidence "
                         f"output is trained, not a family of models; the exported model is "
                         f"an {MODEL_FAMILY} model (its model.json says so)")

    def net_config(self, cfg, dataset):
        from apcg_core.nn.apcg_plus import PlusConfig
        if cfg.init is None:
            raise InputError(f"the {NAME} family trains the incidence output of an APCG+ "
                             "model: give the model with --init MODEL")
        return PlusConfig(n_types=len(dataset.types), width=cfg.width, sheet=cfg.sheet,
                          head=cfg.head, outputs=1)

    def init_from(self, net, model_dir, dataset) -> None:
        """Every weight of the model's network but the last layer's (one channel here, two
        there), which starts at zero: a cosine of one half everywhere."""
        import torch
        model = self.starting_model(net, model_dir, dataset)
        own = model.torch_net().state_dict()
        start = {k: v for k, v in own.items() if not k.startswith("head.")}
        net.load_state_dict(start, strict=False)
        with torch.no_grad():
            net.head.weight.zero_()
            net.head.bias.zero_()

    def prepare(self, dataset) -> None:
        if getattr(dataset, "cos_incidence", None) is None:
            raise InputError(f"dataset {dataset.directory} holds no cos_incidence: build it "
                             "with incidence = true in its config (docs/DATASET.md)")
        super().prepare(dataset)

    def draw(self, tr, idx, rng):
        """Query cells drawn as the model's training draws them, and their targets: is a
        return, its cosine of incidence."""
        u, v, hit, _, cos = draw_queries(tr.data, idx, rng, cosine=True)
        return u, v, hit, cos

    def train_step(self, tr) -> dict:
        import torch
        read, (hit, cos) = self.read_queries(tr)
        err = torch.abs(torch.sigmoid(read[:, 0]) - cos) * hit
        n = hit.sum().clamp(min=1.0)
        l1 = err.sum() / n
        self.descend(tr, l1)
        right = ((err < CLOSE).float() * hit).sum() / n
        return tr.finish_step(l1, l1, 0.0, right)

    def export_reads(self, state: dict) -> list[str]:
        base = state["train"].get("init")
        return [base] if base else []

    def export(self, state: dict, header: dict, out_dir, meta: dict, data_dir,
               sampling_steps=None) -> Path:
        """The ``--init`` model's directory again, with ``incidence.onnx`` and, in model.json,
        ``incidence``: this network and how it was trained."""
        from apcg_core.families import load_model
        from apcg_core.nn.apcg_plus import PlusConfig, PlusNet
        self.check_sampling_steps(sampling_steps, state)
        base = state["train"].get("init")
        if not base or not (Path(base) / "model.json").is_file():
            raise InputError(f"the run's --init model {base!r} is not there any more: the "
                             "incidence network is exported beside the model it was trained "
                             "for")
        model = load_model(base)
        net = PlusNet(PlusConfig.from_dict(state["net"]))
        net.load_state_dict(state["G"])
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        for f in sorted(Path(base).iterdir()):
            if f.is_file() and not f.name.startswith(self.record_prefix) \
                    and f.name != "incidence.onnx":
                shutil.copy(f, out / f.name)
        export_sheets_onnx(net, out / "incidence.onnx", output="incidence")
        record = {k: meta[k] for k in ("net", "trained_steps", "trained_epochs", "dataset",
                                       "train", "generator_weights") if k in meta}
        full = {**without_incidence(model.meta), "incidence": record}
        (out / "model.json").write_text(json.dumps(full, indent=1) + "\n")
        return out


INCIDENCE = IncidenceFamily()

__all__ = ["INCIDENCE", "IncidenceFamily"]
