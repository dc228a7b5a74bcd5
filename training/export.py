"""A training run's checkpoint -> a model directory (model.json + generator.onnx)."""

from __future__ import annotations

import json
import os
import shutil
import warnings
from pathlib import Path

import numpy as np
import torch

from apcg_core.depth import TAU_DEFAULT
from apcg_core.errors import InputError
from apcg_core.io.dataset import read_header
from apcg_core.nn import Generator, NetConfig


def export_onnx(g: Generator, path: Path) -> None:
    g = g.eval()
    z = torch.zeros(2, 100)
    nu = torch.zeros(2, 6)
    tmp = path.with_name(path.name + ".part")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(g, (z, nu), str(tmp), input_names=["noise", "nu"],
                          output_names=["image"], opset_version=17, dynamo=False,
                          do_constant_folding=False,
                          dynamic_axes={"noise": {0: "batch"}, "nu": {0: "batch"},
                                        "image": {0: "batch"}})
    os.replace(tmp, path)


def export_model(run_dir, out_dir, tau: float = TAU_DEFAULT, data_dir=None,
                 checkpoint=None, raw: bool = False, sampling_steps: int | None = None) -> Path:
    """``checkpoint``: a kept copy (e.g. checkpoints/step-001000.pt) instead of the latest.
    The generator's moving average is exported when the run kept one, the raw weights when
    ``raw`` or when it did not. ``sampling_steps`` (diffusion only) records how many of the
    schedule's steps generation takes by default (fewer: faster, coarser)."""
    run = Path(run_dir)
    ck = Path(checkpoint) if checkpoint else run / "checkpoint.pt"
    if not ck.exists():
        raise InputError(f"{ck} does not exist: nothing to export")
    st = torch.load(ck, map_location="cpu", weights_only=False)
    cfg = json.loads((run / "train_config.json").read_text())
    head = read_header(data_dir or cfg["data"])
    family = st["train"].get("family", "cgan")
    if sampling_steps is not None:  # checked before anything is written
        if family != "diffusion":
            raise InputError(f"sampling_steps applies to the diffusion family only; {ck} is "
                             f"a {family} run")
        from .baselines.nets import check_sampling_steps
        check_sampling_steps(sampling_steps, st["train"]["diffusion_steps"])
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    averaged = st.get("G_ema") is not None and not raw
    if averaged:
        st["G"] = st["G_ema"]
    if family == "cgan":
        g = Generator(NetConfig(**st["net"]))
        g.load_state_dict(st["G"])
        export_onnx(g, out / "generator.onnx")
    meta = {"format": "apcg-model", "format_version": 1, "net": st["net"],
            "condition_space": head["condition_space"], "lidar": head["lidar"],
            "types": [{k: t[k] for k in ("code", "name", "catalog_index", "kind", "range_band",
                                          "depth_length_m")} for t in head["types"]],
            "tau": tau, "trained_steps": st["step"],
            "trained_epochs": round(st["batch_counter"] / max(1, _bpe(head, st)), 3),
            "dataset": head.get("name"), "train": st["train"],
            "norm": bool(st["train"].get("norm", True)),
            "generator_weights": (f"moving average (decay {st['train']['ema']:g}) since step "
                                  f"{st.get('ema_since', 0)}" if averaged else "raw")}
    if family == "cgan":
        (out / "model.json").write_text(json.dumps(meta, indent=1) + "\n")
    else:  # a comparison family: torch weights and the expected-count table
        if family == "diffusion":
            meta["sampling_steps"] = sampling_steps or st["train"]["diffusion_steps"]
        from .baselines.data import CountLookup
        from .baselines.model import export_baseline
        from .data import DepthDataset
        train = DepthDataset(data_dir or cfg["data"], "train")
        counts = CountLookup(train.conditions[:, 0], train.nu, np.diff(train.offsets))
        export_baseline(st, head, counts, out, meta)
    if (run / "train_config.json").exists():
        shutil.copy(run / "train_config.json", out / "train_config.json")
    if (run / "log.csv").exists():  # the log up to the exported step
        lines = (run / "log.csv").read_text().splitlines(keepends=True)
        keep = [lines[0]] + [ln for ln in lines[1:] if int(ln.split(",", 1)[0]) <= st["step"]]
        (out / "log.csv").write_text("".join(keep))
    return out


def _bpe(head, st) -> int:
    return head["n_train"] // st["train"]["batch_size"]
