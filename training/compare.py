"""`apcg compare`: every method side by side, the paper's way (its Figs. 14, 15, 17), from one
command: each model's training budget, its peak memory while training, its generation time per
cloud, its MMD / JSD per slant-range band beside its own untrained network, and its
faithfulness per band beside two simulator references (:mod:`training.faithfulness`, decoys and
references made once for all methods).

    apcg compare --data DIR -o REPORT --model DIR --model DIR ... [--pairs N] [--no-faithfulness]

Writes REPORT/compare.json, REPORT/compare.md and REPORT/compare.png. Memory is measured by
training a few steps of each model's own configuration in a fresh process (the peak of a process
includes everything it ever held, so the models must not share one).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from apcg_core.errors import InputError

from . import protocol
from .figures import read_log
from .protocol import band_mean, band_order, draw_pairs

MEMORY_CHILD = """
import json, resource, sys, time, torch
from training.trainer import Trainer, TrainConfig
spec = json.loads(sys.argv[1])
n = int(sys.argv[4])
cfg = TrainConfig.from_dict({**spec, "steps": n + 1, "checkpoint_every": 10**9,
                             "keep_every": 0})
tr = Trainer(sys.argv[2], sys.argv[3], cfg, progress=False)
tr.train_step()  # warm-up
t0 = time.perf_counter()
for _ in range(n):
    tr.train_step()
dt = (time.perf_counter() - t0) / n
gpu = torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else None
# VmHWM is this process's own high-water mark; Linux carries ru_maxrss over from the parent
# through fork and exec, so it would report the parent's size when that is larger.
try:
    hwm = [ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:")]
    peak = int(hwm[0].split()[1]) / 1024
except (OSError, IndexError):
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"seconds_per_step": dt, "peak_rss_mb": peak, "peak_gpu_mb": gpu}))
"""


MEMORY_TIMEOUT_S = 3600  # a few steps of any preset take seconds to minutes


def training_memory(train_cfg: dict, data_dir, steps: int = 5) -> dict:
    """Peak resident memory (MB) and seconds per step while training ``steps`` steps of a
    configuration (TrainConfig as a dict), in a fresh process."""
    with tempfile.TemporaryDirectory() as tmp:
        # the child runs in the repository root: a path relative to the caller's directory
        # would name another place there
        try:
            r = subprocess.run([sys.executable, "-c", MEMORY_CHILD, json.dumps(train_cfg),
                                str(Path(data_dir).resolve()), str(Path(tmp) / "run"),
                                str(steps)], cwd=Path(__file__).resolve().parents[1],
                               capture_output=True, text=True, timeout=MEMORY_TIMEOUT_S)
        except subprocess.TimeoutExpired:  # the child is killed: nothing waits for ever
            raise RuntimeError(f"memory measurement: {steps} training steps did not finish in "
                               f"{MEMORY_TIMEOUT_S} s") from None
    if r.returncode:
        raise RuntimeError(f"memory measurement failed: {r.stderr[-1500:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def budget(model) -> dict:
    """What a model's training cost: steps, epochs and logged training hours."""
    meta = model.meta
    hours = None
    if (Path(model.directory) / "log.csv").exists():
        hours = float(read_log(model.directory)["hours"][-1])
    train = meta.get("train", {})
    return {"steps": meta.get("trained_steps"), "epochs": meta.get("trained_epochs"),
            "hours": hours, "batch_size": train.get("batch_size")}


def method_names(dirs) -> list[tuple[str, str]]:
    """(method name, model directory) for each ``--model DIR``: the name is the directory's."""
    out = [(Path(d).name or str(d), str(d)) for d in dirs]
    names = [n for n, _ in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"--model directories must have different names (a method is named "
                         f"after its directory); {dup} appear more than once")
    return out


def compare(models, data_dir, n_pairs: int | None = protocol.DEFAULT_PAIRS, seed: int = 0,
            memory_steps: int = 5, with_untrained: bool = True, progress: bool = False,
            faithfulness: bool = True) -> dict:
    """``models``: (name, loaded model) pairs. Every model is scored on the same pairs, by the
    evaluation protocol (with faithfulness: against the same decoys, beside the references)."""
    pairs = draw_pairs(data_dir, n_pairs, seed, half="test")
    keep = ("pairs", "scored", "no_score", "mmd", "jsd", "points_standard",
            "points_generated", "points_ratio_p10_p50_p90") + (
        ("faithfulness",) if faithfulness else ())
    prep = None
    if faithfulness:
        from .faithfulness import prepare
        if progress:
            print("faithfulness: decoys and references", file=sys.stderr, flush=True)
        prep = prepare(pairs)
    rows = []
    for name, model in models:
        if progress:
            print(f"{name}: scoring", file=sys.stderr, flush=True)
        rep = protocol.score(model, pairs, floor=False, pointflow=False,
                             faithfulness=prep or False)
        row = {"method": name, "model": str(model.directory), "family": model.family,
               "budget": budget(model),
               "ms_per_cloud": round(1e3 * rep["seconds"]["generate"] / rep["pairs"], 3),
               "bands": {b: {k: v[k] for k in keep} for b, v in rep["bands"].items()}}
        if with_untrained:
            with tempfile.TemporaryDirectory() as tmp:
                fresh = protocol.score(protocol.untrained(model, Path(tmp), seed), pairs,
                                       floor=False, pointflow=False)
            for b, v in row["bands"].items():
                v["untrained"] = {k: fresh["bands"][b][k] for k in ("mmd", "jsd")}
        row["mean"] = {k: band_mean(row["bands"], k) for k in ("mmd", "jsd")}
        if faithfulness:
            row["mean"]["faithfulness"] = rep["mean"]["faithfulness"]
        if with_untrained:
            untrained = {b: v["untrained"] for b, v in row["bands"].items()}
            row["mean"]["untrained"] = {k: band_mean(untrained, k) for k in ("mmd", "jsd")}
        if memory_steps and "train" in model.meta:
            if progress:
                print(f"{name}: training memory", file=sys.stderr, flush=True)
            row["training_memory"] = training_memory(model.meta["train"], data_dir,
                                                     memory_steps)
        rows.append(row)
    out = {**pairs.record(), "protocol": protocol.constants(), "rows": rows}
    if prep is not None:
        out["references"] = prep.references
        out["seconds_faithfulness_references"] = round(prep.seconds, 2)
    return out


def _f(v, d=3) -> str:
    return "-" if v is None else f"{v:.{d}f}"


def markdown(report: dict) -> str:
    bands = sorted(report["rows"][0]["bands"], key=band_order)
    head = ["method", "steps", "epochs", "train h", "peak MB", "s/step", "ms/cloud",
            "mean over bands"]
    lines = [f"# Comparison of methods on {report['pairs']} held-out pairs ({report['half']} "
             f"half, seed {report['seed']})", "",
             f"Reproduce: `{report['command']}`", "",
             f"MMD / JSD ({report['protocol']['jsd_bins']}^3 bins) to the standard cloud, per "
             "slant-range band; in brackets the same network untrained. The mean over bands "
             "weighs every band alike and skips bands without a score. Peak MB: the resident "
             "memory of a fresh process training the model's own configuration (CPU, "
             "dataset in memory).", "",
             "| " + " | ".join(head + bands) + " |", "|" + "---|" * (len(head) + len(bands))]
    for r in report["rows"]:
        b, mem = r["budget"], r.get("training_memory", {})
        cells = [r["method"], str(b["steps"]), _f(b["epochs"], 1), _f(b["hours"], 2),
                 _f(mem.get("peak_rss_mb"), 0), _f(mem.get("seconds_per_step"), 2),
                 _f(r["ms_per_cloud"], 2)]
        for v in [r["mean"]] + [r["bands"][name] for name in bands]:
            u = v.get("untrained")
            cells.append(f"{_f(v['mmd'])} / {_f(v['jsd'], 2)}" + (
                f" ({_f(u['mmd'])} / {_f(u['jsd'], 2)})" if u else ""))
        lines.append("| " + " | ".join(cells) + " |")
    # MMD and JSD compare normalised distributions: a cloud with a tenth of the points the
    # lidar records can score well. The counts say what the metrics do not.
    lines += ["", "Points per cloud, generated / standard (means per band; MMD and JSD compare "
              "distributions and do not see a cloud that is too sparse or too dense):", "",
              "| " + " | ".join(["method"] + bands) + " |", "|" + "---|" * (1 + len(bands))]
    for r in report["rows"]:
        cells = [r["method"]] + [f"{_f(r['bands'][n]['points_generated'], 0)} / "
                                 f"{_f(r['bands'][n]['points_standard'], 0)}" for n in bands]
        lines.append("| " + " | ".join(cells) + " |")
    lines += faithfulness_lines(report, bands)
    return "\n".join(lines) + "\n"


def faithfulness_lines(report: dict, bands: list) -> list[str]:
    """Per method and reference, per band: the faithful share (closer than the yaw decoy /
    than the other type) and MMD."""
    refs = report.get("references")
    if not refs:
        return []

    def cell(b):
        f = b.get("faithfulness") if b else None
        if not f or f["share"] is None:
            return "-"
        return (f"{100 * f['share']:.0f}% ({100 * f['share_vs_yaw']:.0f}% / "
                f"{100 * f['share_vs_other_type']:.0f}%), MMD {_f(b['mmd'])}")

    def mean(m):
        v = m.get("faithfulness", {}).get("all")
        return "-" if v is None else f"{100 * v:.0f}%"
    lines = ["", "Faithfulness (SPEC section 9): the share of scorable pairs whose cloud is "
             "closer (MMD) to its own standard cloud than to the same type at yaw +-45 deg and "
             "to a type of another category (in brackets each alone), the same decoys for every "
             "method; the references simulate their clouds (point z-buffer, embree 2 x 2):", "",
             "| " + " | ".join(["method", "mean over bands"] + bands) + " |",
             "|" + "---|" * (2 + len(bands))]
    for name, r in [(r["method"], r) for r in report["rows"]] + [
            (f"{n} (reference)", v) for n, v in refs.items()]:
        cells = [name, mean(r["mean"])] + [cell(r["bands"].get(b)) for b in bands]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def plot(report: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), constrained_layout=True)
    bands = sorted(report["rows"][0]["bands"], key=band_order)
    for col, kind in enumerate(("aircraft", "drone")):
        names = [n for n in bands if n.startswith(kind)]
        x = np.arange(len(names))
        for row, metric in enumerate(("mmd", "jsd")):
            ax = axes[row, col]
            for r in report["rows"]:
                # None (no score) is a gap; a score of 0.0 is a point
                ax.plot(x, [np.nan if r["bands"][n][metric] is None else r["bands"][n][metric]
                            for n in names], "o-",
                        label=r["method"])
            ax.set_xticks(x, [n.split(" ", 1)[1] for n in names], rotation=20)
            bins = report["protocol"]["jsd_bins"]
            ax.set_title(f"{kind}: {metric.upper()}"
                         + (f" ({bins}^3 bins)" if metric == "jsd" else ""))
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
    fig.suptitle("Every method against the simulator per slant-range band (paper Fig. 17)")
    from apcg_core.io.atomic import atomic_path
    with atomic_path(path, ".part" + Path(path).suffix) as tmp:  # matplotlib reads the format
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def write(report: dict, out_dir) -> Path:
    from apcg_core.io.dataset import write_atomic
    out = Path(out_dir)
    write_atomic(out / "compare.json", (json.dumps(report, indent=1) + "\n").encode())
    write_atomic(out / "compare.md", markdown(report).encode())
    plot(report, out / "compare.png")
    return out
