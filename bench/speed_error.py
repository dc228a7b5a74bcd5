"""Speed against error: time per point cloud against MMD and JSD to the exact reference, per
slant-range band, for every way this project makes clouds, measured in one run.

    .venv/bin/python bench/speed_error.py --data data/cpu [--per-band 24] [--model DIR ...]
        [--json bench/results/speed_error.json] [--plot docs/speed_error.png]
        [--recognize recognize.json] [--markdown table.md] [--force]

The reference is the standard cloud of each held-out condition (the dataset's test split: one
ray through each cell centre, embree, quantized ranges). Methods:

* ``embree`` / ``blender``: exact ray casting (blender: one Geometry Nodes evaluation per type);
* ``embree kxk``: k x k rays per cell, nearest kept (a beam footprint, not the standard);
* ``points``: the paper's z-buffer over a 10,000-point fine cloud;
* ``APCG <model>``: generation, batched (the default model unless --model is given);
* ``nearest sample``: the training sample of the same type nearest in condition space (nu), its
  cloud moved along the line of sight to the query's range (a lookup, no model).

Time is wall time per cloud in one process, batched per type where the method allows, meshes
and models loaded beforehand. Every row carries its point counts; JSD carries its bins. Per
band also each method's faithfulness (training/faithfulness.py: closer to its own standard
cloud than to both decoys, the decoys simulated once for every method). ``--recognize`` takes a
report of `apcg benchmark recognize` and puts each source's TSTR ratio beside its method (exact
-> embree, points, embree-2x2 -> embree 2x2, a model directory -> its row): the usefulness of
the clouds for training a recognizer, measured by that run.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.frames import cartesian_to_spherical, spherical_to_cartesian  # noqa: E402
from training import protocol  # noqa: E402
from training.data import DepthDataset  # noqa: E402

# simulated: one backend's clouds, timed; decoys and judge: faithfulness
from training.faithfulness import decoys, judge, mean_shares, simulated  # noqa: E402
from training.faithfulness import summarise as faithful_share  # noqa: E402


def generated(model, ds, idx, seed: int = 0):
    cond = ds.condition_rows(idx)  # mapped into the model's types by name
    model.generate(cond[:8], seed=seed)  # warm the runtime
    t0 = time.perf_counter()
    res = model.generate(cond, count=1, seed=seed)
    dt = time.perf_counter() - t0
    return [c.xyz for c in res.cloud.split(len(idx))], dt / len(idx)


def nearest_sample(ds_train, ds, idx):
    """The same type's training sample nearest in nu, moved to the query's range."""
    t0 = time.perf_counter()
    out = []
    for i in idx:
        same = np.flatnonzero(ds_train.conditions[:, 0] == ds.conditions[i, 0])
        d = np.abs(ds_train.nu[same, 1:] - ds.nu[i, 1:]).sum(axis=1)
        j = int(same[np.argmin(d)])
        a, b, r = cartesian_to_spherical(ds_train.standard_cloud(j))
        shift = ds.conditions[i, 1] - ds_train.conditions[j, 1]
        out.append(spherical_to_cartesian(a, b, r + shift))
    return out, (time.perf_counter() - t0) / len(idx)


def score(refs, clouds, bands, dec, seed: int = 0) -> dict:
    """Per band, the evaluation protocol's scores (training/protocol.py) and faithfulness
    against the pairs' decoys ``dec``."""
    per: dict = {}
    verdicts: dict = {}
    for k, (ref, c) in enumerate(zip(refs, clouds, strict=True)):
        row = protocol.score_pair(ref, c, seed + k)
        per.setdefault(bands[k], []).append(row)
        verdicts.setdefault(bands[k], []).append(
            judge(ref, c, dec.yaw[k], dec.other[k], seed + k, row["mmd"]))
    return {name: {**protocol.summarise(per[name]),
                   "faithfulness": faithful_share(verdicts[name])}
            for name in sorted(per, key=protocol.band_order)}


# `apcg benchmark recognize` source names of the methods here (a model: its directory)
RECOGNIZE_SOURCE = {"embree": "exact", "points": "points", "embree 2x2": "embree-2x2"}


def tstr_of(recognize: dict, name: str, directory: str | None) -> dict | None:
    """The TSTR ratio (overall, with its interval) of this method in a recognize report."""
    if name == "embree":
        return {"ratio": 1.0, "ci": [1.0, 1.0], "reference": True}
    want = RECOGNIZE_SOURCE.get(name, directory)
    for s in recognize.get("sources", []):
        src = s["source"]["source"] if isinstance(s["source"], dict) else s["source"]
        same_dir = want is not None and Path(str(src)).resolve() == Path(str(want)).resolve()
        if same_dir or src == want:
            return dict(s["tstr"]["overall"])
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--per-band", type=int, default=24)
    ap.add_argument("--model", action="append", help="model directory (repeatable; default: "
                                                    "the shipped default model)")
    ap.add_argument("--backends", default="embree,blender,points")
    ap.add_argument("--supersample", default="2,3")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json")
    ap.add_argument("--plot")
    ap.add_argument("--recognize", help="recognize.json of `apcg benchmark recognize`: its "
                                        "TSTR ratios beside the methods")
    ap.add_argument("--markdown", help="write the summary and per-band tables here too")
    ap.add_argument("--force", action="store_true",
                    help="replace the --markdown and --plot files")
    args = ap.parse_args()
    from bench_output import emit, refuse, write_text
    if args.markdown and any(o and Path(o).resolve() == Path(args.markdown).resolve()
                             for o in (args.json, args.plot)):
        ap.error(f"--markdown {args.markdown} is also the --json or --plot file")
    refuse([args.markdown, args.plot], args.force, [args.recognize, args.data])
    from apcg_core.families import load_model
    models = [load_model(m) for m in (args.model or [None])]
    n_bands = 9
    pairs = protocol.draw_pairs(args.data, args.per_band * n_bands, args.seed, half="test")
    ds, idx, bands = pairs.ds, pairs.idx, pairs.bands
    refs = [ds.standard_cloud(int(i)) for i in idx]
    dec = decoys(ds, idx, args.seed + np.arange(len(idx)))  # the protocol's pair seeds
    methods = {}
    directories = {}
    for b in args.backends.split(","):
        methods[b] = simulated(b, ds, idx)
    for k in (int(x) for x in args.supersample.split(",") if x):
        methods[f"embree {k}x{k}"] = simulated("embree", ds, idx, supersample=k)
    for m in models:
        methods[f"{m.family} {Path(m.directory).name}"] = generated(m, ds, idx, args.seed)
        directories[f"{m.family} {Path(m.directory).name}"] = str(m.directory)
    methods["nearest sample"] = nearest_sample(DepthDataset(args.data, "train"), ds, idx)
    report = {"command": "python bench/speed_error.py " + shlex.join(sys.argv[1:]),
              **pairs.record(), "protocol": protocol.constants(),
              "jsd_bins": protocol.JSD_BINS, "methods": {}}
    recognize = json.loads(Path(args.recognize).read_text()) if args.recognize else None
    if recognize is not None:
        report["recognize"] = recognize.get("command")
    for name, (clouds, sec) in methods.items():
        b = score(refs, clouds, bands, dec, args.seed)
        report["methods"][name] = {
            "ms_per_cloud": round(1e3 * sec, 3), "bands": b,
            "mean": {"mmd": _mean(b, "mmd"), "jsd": _mean(b, "jsd"),
                     "faithfulness": mean_shares(b)},
            "tstr": None if recognize is None else tstr_of(recognize, name,
                                                           directories.get(name))}
        print(name, report["methods"][name]["ms_per_cloud"], "ms/cloud", flush=True)
    emit(report, args.json, show=False)
    text = summary(report) + "\n\n" + markdown(report)
    print(text)
    if args.markdown:
        write_text(args.markdown, text + "\n")
    if args.plot:
        plot(report, Path(args.plot))
    return 0


def _mean(bands: dict, key: str):
    vals = [b[key] for b in bands.values() if b[key] is not None]
    return float(np.mean(vals)) if vals else None


def summary(report: dict) -> str:
    """One row per method: time, the means over bands (each band alike) and usefulness."""
    lines = ["| method | ms / cloud | mean MMD | mean JSD | faithful: aircraft / drones "
             "| recognition (TSTR) [95%] |", "|---|---|---|---|---|---|"]
    for name, m in report["methods"].items():
        f = m["mean"]["faithfulness"]
        t = m.get("tstr")
        tstr = "-" if t is None else (f"{t['ratio']:.3f}" + ("" if t.get("reference")
                                      else f" [{t['ci'][0]:.3f}, {t['ci'][1]:.3f}]"))
        pct = ["-" if f[k] is None else f"{f[k]:.0%}" for k in ("aircraft", "drone")]
        lines.append(f"| {name} | {m['ms_per_cloud']:.2f} | {m['mean']['mmd']:.4f} | "
                     f"{m['mean']['jsd']:.2f} | {pct[0]} / {pct[1]} | {tstr} |")
    return "\n".join(lines)


def markdown(report: dict) -> str:
    lines = ["| method | ms / cloud | " + " | ".join(
        f"{b} MMD / JSD" for b in next(iter(report["methods"].values()))["bands"]) + " |"]
    lines.append("|---|---|" + "---|" * len(next(iter(report["methods"].values()))["bands"]))
    for name, m in report["methods"].items():
        cells = [("-" if v["mmd"] is None else f"{v['mmd']:.3f}") + " / "
                 + ("-" if v["jsd"] is None else f"{v['jsd']:.2f}") for v in m["bands"].values()]
        lines.append(f"| {name} | {m['ms_per_cloud']:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(report: dict, path: Path) -> None:
    import matplotlib
    from bench_output import save_figure
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), constrained_layout=True)
    colours = plt.get_cmap("tab20").colors  # ten default colours repeat beyond ten methods
    markers = "DosP^vX*<>h"
    for ax, metric in zip(axes, ("mmd", "jsd"), strict=True):
        for i, (name, m) in enumerate(report["methods"].items()):
            vals = [v[metric] for v in m["bands"].values() if v[metric] is not None]
            # tab20 pairs a dark and a light shade: the ten dark ones first, then the light
            c = colours[2 * i % 20 + (2 * i // 20) % 2]
            ax.scatter([m["ms_per_cloud"]] * len(vals), vals, s=10, color=c, alpha=0.5)
            ax.scatter([m["ms_per_cloud"]], [np.mean(vals)], marker=markers[i % len(markers)],
                       s=55, color=c, edgecolor="black", linewidth=0.5, label=name)
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # no crowded labels
        ax.set_xlabel("ms per cloud (this machine, one process)")
        ax.set_ylabel(metric.upper() + (f" ({report['jsd_bins']}^3 bins)"
                                        if metric == "jsd" else "") + " to the exact reference")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("Speed against error, per slant-range band (dots) and mean (large marks)")
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
