"""The paper's training figures, each a PNG plus the data behind it (JSON):

    apcg figure 13 --run RUN -o fig13.png     |L_D| and L_G per epoch, from the training log
    apcg figure 14 --run RUN --data DIR -o fig14.png
                                              MMD and JSD against training time, one point per
                                              kept checkpoint (checkpoints/step-*.pt)
"""

from __future__ import annotations

import csv
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from apcg_core.errors import InputError


def read_log(run) -> dict:
    """The log's columns as arrays; ``hours`` is training time summed over resumed runs (logs
    written before the clock carried over restart at 0 on resume: such drops are joined)."""
    path = Path(run) / "log.csv"
    if not path.exists():
        raise InputError(f"{run} has no log.csv")
    with open(path) as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise InputError(f"{path} has no rows yet")
    cols = {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}
    sec = cols["seconds"]
    step = np.diff(sec, prepend=0.0)
    step[step < 0] = sec[step < 0]  # a resumed run that counted from 0 again
    cols["hours"] = np.cumsum(step) / 3600.0
    return cols


def fig13(run, out) -> dict:
    """|L_D| and L_G averaged per epoch (the paper's Fig. 13)."""
    log = read_log(run)
    epoch = np.floor(log["epoch"] - 1e-9).astype(int)
    epochs = np.unique(epoch)
    data = {"epoch": (epochs + 1).tolist(),
            "abs_loss_d": [float(np.abs(log["loss_d"][epoch == e]).mean()) for e in epochs],
            "loss_g": [float(log["loss_g"][epoch == e].mean()) for e in epochs],
            "gp": [float(log["gp"][epoch == e].mean()) for e in epochs]}
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    ax.plot(data["epoch"], data["abs_loss_d"], label="|L_D|")
    ax.plot(data["epoch"], data["loss_g"], label="L_G")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss (mean over the epoch)")
    ax.set_title(f"Training losses of {Path(run).name} (paper Fig. 13)")
    ax.grid(alpha=0.3)
    ax.legend()
    _save(fig, out, data)
    return data


def fig14(run, data_dir, out, n_pairs: int = 400, seed: int = 0) -> dict:
    """Mean MMD and JSD (all bands) of each kept checkpoint against training time."""
    from apcg_core.generation import APCGModel

    from .data import DepthDataset
    from .export import export_model
    from .quick_eval import evaluate
    snaps = sorted((Path(run) / "checkpoints").glob("step-*.pt"))
    if not snaps:
        raise InputError(f"{run} has no kept checkpoints (train with --keep-every)")
    log = read_log(run)
    ds = DepthDataset(data_dir, "test")
    rows = []
    for snap in snaps:
        step = int(snap.stem.split("-")[1])
        with tempfile.TemporaryDirectory() as tmp:
            model = APCGModel(export_model(run, tmp, checkpoint=snap), runtime="onnx")
            bands = evaluate(model, ds, n_pairs, seed)
        at = np.searchsorted(log["step"], step)
        hours = float(log["hours"][min(at, len(log["hours"]) - 1)])
        mmds = [b["mmd"] for b in bands.values() if b["mmd"] is not None]
        jsds = [b["jsd"] for b in bands.values() if b["jsd"] is not None]
        rows.append({"step": step, "hours": hours, "mmd": float(np.mean(mmds)),
                     "jsd": float(np.mean(jsds))})
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    data = {"rows": rows, "pairs": n_pairs, "seed": seed}
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    h = [r["hours"] for r in rows]
    ax.plot(h, [r["mmd"] for r in rows], "o-", label="MMD")
    ax.plot(h, [r["jsd"] for r in rows], "s-", label="JSD")
    ax.set_xlabel("training time (h, this machine)")
    ax.set_title(f"MMD and JSD against training time, {Path(run).name} (paper Fig. 14)")
    ax.grid(alpha=0.3)
    ax.legend()
    _save(fig, out, data)
    return data


def _save(fig, out, data) -> None:
    import matplotlib.pyplot as plt
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    out.with_suffix(".json").write_text(json.dumps(data, indent=1) + "\n")
