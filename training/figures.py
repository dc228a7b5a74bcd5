"""The paper's training figures, each a PNG plus the data behind it (JSON):

    apcg figure 13 --run RUN -o fig13.png     |L_D| and L_G per epoch, from the training log
    apcg figure 14 --run [NAME=]RUN ... --data DIR [--tau T] -o fig14.png
                                              MMD and JSD against training time, one point per
                                              kept checkpoint (checkpoints/step-*.pt), one line
                                              per run (any model family)
    apcg figure 18 [--model DIR] -o fig18.png  generation time against the number of clouds,
                                              for 2, 4 and 8 types and random counts
    apcg figure 19 [--model DIR] --data DIR -o fig19.png
                                              MMD and JSD of generated clouds against slant
                                              range, scored against the standard clouds and
                                              against their cell-jittered ("noised") copies
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from apcg_core.errors import InputError
from apcg_core.io.atomic import atomic_path
from apcg_core.io.csv_table import read_csv
from apcg_core.io.dataset import write_atomic


def read_log(run) -> dict:
    """The log's columns as arrays; ``hours`` is training time summed over resumed runs (logs
    written before the clock carried over restart at 0 on resume: such drops are joined)."""
    path = Path(run) / "log.csv"
    if not path.exists():
        raise InputError(f"{run} has no log.csv")
    table = read_csv(path, required=("seconds",), what="training log")
    if not table.rows:
        raise InputError(f"{path} has no rows yet")
    cols = {k: np.array([r.float(k) for r in table]) for k in table.header if k}
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
    data = {"command": f"apcg figure 13 --run {_rel(run)} -o {_rel(out)}",
            "epoch": (epochs + 1).tolist(),
            "abs_loss_d": [float(np.abs(log["loss_d"][epoch == e]).mean()) for e in epochs],
            "loss_g": [float(log["loss_g"][epoch == e].mean()) for e in epochs],
            "gp": [float(log["gp"][epoch == e].mean()) for e in epochs]}
    _lines([(data["epoch"], data["abs_loss_d"], "-", "|L_D|"),
            (data["epoch"], data["loss_g"], "-", "L_G")], "epoch",
           "loss (mean over the epoch)", f"Training losses of {Path(run).name} (paper Fig. 13)",
           out, data)
    return data


def fig14(runs, data_dir, out, n_pairs: int = 400, seed: int = 0, tau: float | None = None,
          max_checkpoints: int | None = None) -> dict:
    """Mean MMD and JSD (all bands) of each kept checkpoint against training time, for one run
    or several ({name: run} or [(name, run)]; any model family), on the same held-out pairs.

    ``tau`` is the Im2PC threshold the cGAN checkpoints are exported with (default: the export
    default); score a shipped model's run at the tau chosen for it. ``max_checkpoints`` scores at
    most that many per run, evenly spaced and always the last (a slow sampler with many kept
    checkpoints otherwise takes most of the time)."""
    from apcg_core.families import load_model

    from . import protocol
    from .export import export_model
    if isinstance(runs, (str, Path)):
        runs = [(Path(runs).name, runs)]
    runs = list(runs.items()) if isinstance(runs, dict) else list(runs)
    tau = None if tau is None else float(tau)  # None: each family's export default
    pairs = protocol.draw_pairs(data_dir, n_pairs, seed, half="test")
    table = {}
    for name, run in runs:
        snaps = sorted((Path(run) / "checkpoints").glob("step-*.pt"))
        if not snaps:
            raise InputError(f"{run} has no kept checkpoints (train with --keep-every)")
        snaps = [snaps[i] for i in spaced(len(snaps), max_checkpoints)]
        log = read_log(run)
        rows = table[name] = []
        for snap in snaps:
            step = int(snap.stem.split("-")[1])
            with tempfile.TemporaryDirectory() as tmp:
                model = load_model(export_model(run, tmp, tau=tau, checkpoint=snap, force=True))
                mean = protocol.score(model, pairs, floor=False, pointflow=False)["mean"]
            at = np.searchsorted(log["step"], step)
            hours = float(log["hours"][min(at, len(log["hours"]) - 1)])
            rows.append({"step": step, "hours": hours, "mmd": mean["mmd"], "jsd": mean["jsd"]})
            print(json.dumps({"run": name, **rows[-1]}), file=sys.stderr, flush=True)
    limit = "" if max_checkpoints is None else f" --max-checkpoints {max_checkpoints}"
    data = {"runs": table, **pairs.record(), "protocol": protocol.constants(), "tau": tau,
            "max_checkpoints": max_checkpoints,
            "command": "apcg figure 14 " + " ".join(f"--run {n}={_rel(r)}" for n, r in runs)
            + f" --data {_rel(data_dir)} --pairs {n_pairs}"
            + ("" if tau is None else f" --tau {tau:g}") + f"{limit} -o {_rel(out)}"}
    series = []
    for name, rows in table.items():
        h = [r["hours"] for r in rows]
        label = "" if len(table) == 1 else f" {name}"
        # a checkpoint with no scorable pair (all clouds empty) leaves a gap, not a zero
        series += [(h, [_nan(r["mmd"]) for r in rows], "o-", "MMD" + label),
                   (h, [_nan(r["jsd"]) for r in rows], "s--", "JSD" + label)]
    title = next(iter(table)) if len(table) == 1 else "all methods"
    _lines(series, "training time (h, this machine)", "",
           f"MMD and JSD against training time, {title} (paper Fig. 14)", out, data)
    return data


def spaced(n: int, k: int | None) -> list[int]:
    """Indices of at most ``k`` of ``n`` items, evenly spaced, the last always among them."""
    if k is not None and k < 1:
        raise InputError(f"max_checkpoints must be >= 1, got {k}")
    if k is None or k >= n:
        return list(range(n))
    return sorted({int(i) for i in np.round(np.linspace(n - 1, 0, k))})


def _nan(v):
    return float("nan") if v is None else v


def fig18(model, out, counts=(100, 300, 1000, 3000), seed: int = 0) -> dict:
    """Seconds to generate N clouds (noise to point clouds) for 2, 4 and 8 types, the N
    conditions drawn at random over Table 1 (the paper's Fig. 18; it claims < 6 s for 10^6 on a
    GPU)."""
    import time
    rng = np.random.default_rng(seed)
    model.generate(_random_table(model, 8, 1, rng), seed=seed)  # warm the runtime
    rows = []
    type_counts = [t for t in (2, 4, 8) if t <= len(model.types)] or [len(model.types)]
    for n_types in type_counts:
        for n in counts:
            table = _random_table(model, n, n_types, rng)
            t0 = time.perf_counter()
            res = model.generate(table, count=1, seed=seed)
            rows.append({"types": n_types, "clouds": n, "seconds": time.perf_counter() - t0,
                         "points": len(res.cloud)})
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    data = {"command": f"apcg figure 18 --model {_rel(model.directory)} -o {_rel(out)}",
            "rows": rows, "runtime": model.runtime, "model": str(model.directory)}
    series = []
    for n_types in type_counts:
        r = [x for x in rows if x["types"] == n_types]
        series.append(([x["clouds"] for x in r], [x["seconds"] for x in r], "o-",
                       f"{n_types} types"))
    _lines(series, "point clouds generated", "seconds (this machine, CPU)",
           f"Generation time ({model.runtime}; paper Fig. 18)", out, data, log=True)
    return data


def _random_table(model, n: int, n_types: int, rng):
    """n random conditions over the model's condition space, types drawn from n_types."""
    from apcg_core.typetable import Conditions
    codes = rng.choice(len(model.types), n_types, replace=False)
    table = model.space.decode(rng.uniform(-1, 1, (n, 6)))
    table[:, 0] = rng.choice(codes, n)
    lo, hi = model.space.range_bounds(table[:, 0].astype(int))  # the type's own range band
    table[:, 1] = lo + rng.random(n) * (hi - lo)
    return Conditions(model.types, table)


def fig19(model, data_dir, out, n_pairs: int = 600, seed: int = 0, n_bins: int = 10) -> dict:
    """MMD and JSD of generated clouds, scored against the standard clouds ("standard") and
    against their cell-jittered copies ("noised"), per slant-range bin (the paper's Fig. 19)."""
    from . import protocol
    pairs = protocol.draw_pairs(data_dir, n_pairs, seed, half="test")
    ds, idx = pairs.ds, pairs.idx
    table = ds.conditions[idx]
    gen, _ = protocol.generate(model, pairs)
    near = ds.is_near(idx)
    data = {"command": f"apcg figure 19 --model {_rel(model.directory)} --data {_rel(data_dir)} "
                       f"--pairs {n_pairs} --seed {seed} -o {_rel(out)}",
            **pairs.record(), "protocol": protocol.constants()}
    for kind in ("aircraft", "drone"):
        sel = np.flatnonzero(near == (kind == "drone"))
        if len(sel) == 0:
            continue
        edges = np.linspace(table[sel, 1].min(), table[sel, 1].max() + 1e-6, n_bins + 1)
        rows = []
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            ks = [k for k in sel if lo <= table[k, 1] < hi]
            if not ks:
                continue
            vals = {"standard": [], "noised": []}
            for k in ks:
                i = int(idx[k])
                std = ds.standard_cloud(i)
                jit = protocol.jittered(ds, i, seed + int(k))
                for name, ref in (("standard", std), ("noised", jit)):
                    sc = protocol.score_pair(ref, gen[k], seed)
                    vals[name].append((sc["mmd"], sc["jsd"]))
            row = {"range_m": float((lo + hi) / 2), "pairs": len(ks)}
            for name, v in vals.items():
                for j, metric in enumerate(("mmd", "jsd")):
                    x = [p[j] for p in v if p[j] is not None]
                    row[f"{metric}_{name}"] = float(np.mean(x)) if x else None
            rows.append(row)
        data[kind] = rows
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 2, figsize=(10, 6), constrained_layout=True)
    for col, kind in enumerate(("aircraft", "drone")):
        for row_i, metric in enumerate(("mmd", "jsd")):
            ax = axes[row_i, col]
            for name, style in (("standard", "o-"), ("noised", "s--")):
                pts = [(r["range_m"], r[f"{metric}_{name}"]) for r in data.get(kind, [])
                       if r[f"{metric}_{name}"] is not None]
                if pts:
                    ax.plot(*zip(*pts, strict=True), style, label=name)
            ax.set_title(f"{kind}: {metric.upper()}")
            ax.set_xlabel("slant range (m)")
            ax.grid(alpha=0.3)
            if ax.get_lines():
                ax.legend()
            else:  # no scored pair of this kind (a small dataset): say so, not an empty key
                ax.text(0.5, 0.5, f"no {kind} pair scored here (too few test pairs)",
                        ha="center", va="center", transform=ax.transAxes, color="gray")
    fig.suptitle("Generated clouds against standard and cell-jittered clouds (paper Fig. 19)")
    _save(fig, out, data, dpi=100)
    return data


def _lines(series, xlabel: str, ylabel: str, title: str, out, data, log: bool = False):
    """One line plot of (x, y, style, label) series, saved with its data."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    for x, y, style, label in series:
        ax.plot(x, y, style, label=label)
    if log:
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    _save(fig, out, data)


def _rel(path) -> str:
    """A path as a command line would give it: relative to the working directory when inside
    it."""
    import os
    p = os.path.abspath(path)
    return os.path.relpath(p) if p.startswith(os.getcwd() + os.sep) else str(path)


def _save(fig, out, data, dpi: int = 110) -> None:
    import matplotlib.pyplot as plt
    out = Path(out)
    with atomic_path(out, ".part" + out.suffix) as tmp:  # matplotlib reads the format there
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    write_atomic(out.with_suffix(".json"), (json.dumps(data, indent=1) + "\n").encode())


FIG16_TYPES = ("A320neo", "777-300ER", "F-16C Fighting Falcon", "UH-60 Black Hawk",
               "Matrice 300 RTK", "Mavic 3")
FIG16_RANGES_M = {"far": (4500.0, 9000.0, 15000.0), "near": (150.0, 350.0, 550.0)}
FIG16_POSE_DEG = {"elevation": 3.4, "pitch": 2.3, "yaw": 13.2, "roll": 0.13}


def fig16(model, out, types=FIG16_TYPES, pose_deg=None) -> dict:
    """Generated clouds beside the standard ones (the paper's Fig. 16): each type at three
    ranges of its band, seen from the lidar (lateral and vertical offsets from the target's
    centre, metres), the standard cloud (embree) left, the model's right, point counts in the
    titles."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.lidar import DEG
    from dataset_builder.simulate import Simulator
    pose = {**FIG16_POSE_DEG, **(pose_deg or {})}
    missing = [n for n in types if n not in model.types]
    if missing:  # before the simulator starts: the figure's types are its own, not a choice
        listed = ", ".join(repr(n) for n in missing)
        raise InputError(f"figure 16 draws its {len(types)} fixed types ({', '.join(types)}); "
                         f"the model {model.directory} ({model.family}) lacks "
                         f"{listed}: give --model a model that knows all {len(types)} (the "
                         "shipped default does)")
    cat = default_catalog()
    rows = []
    with Simulator("embree", model.lidar) as sim:
        for name in types:
            t = cat.get(name)
            for r in FIG16_RANGES_M[t.range_band]:
                cond = model.condition(t.name, r, pose["elevation"] * DEG, pose["pitch"] * DEG,
                                       pose["yaw"] * DEG, pose["roll"] * DEG)
                std = sim.simulate_type(cat, t.name, cond.table).cloud.xyz
                gen = model.generate(cond, seed=0).cloud.xyz
                rows.append((t.name, r, std, gen))
    fig, axes = plt.subplots(len(types), 6, figsize=(18, 2.1 * len(types)),
                             constrained_layout=True)
    data = {"command": f"apcg figure 16 --model {_rel(model.directory)} -o {_rel(out)}",
            "model": str(model.directory), "pose_deg": pose, "panels": []}
    for k, (name, r, std, gen) in enumerate(rows):
        i, j = divmod(k, 3)
        centre = np.array([0.0, r * np.sin(pose["elevation"] * DEG),
                           r * np.cos(pose["elevation"] * DEG)])
        lim = max(np.abs(std - centre)[:, :2].max(initial=1.0), 1.0) * 1.15
        for c, (cloud, label) in enumerate(((std, "standard"), (gen, model.family))):
            ax = axes[i, 2 * j + c]
            p = cloud - centre
            ax.scatter(p[:, 0], p[:, 1], s=max(0.3, 30.0 / max(len(p), 1) ** 0.5),
                       c="black" if c == 0 else "tab:red", linewidths=0)
            ax.set_xlim(-lim, lim)
            ax.set_ylim(-lim / 2.5, lim / 2.5)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            rng = f"{r / 1000:g} km" if r >= 1000 else f"{r:g} m"
            ax.set_title(f"{name}, {rng}: {label} ({len(p)} pts)", fontsize=7)
        data["panels"].append({"type": name, "range_m": r, "points_standard": len(std),
                               "points_generated": len(gen)})
    fig.suptitle(f"Standard (black) and generated (red) clouds, pose (deg) {pose} "
                 f"(paper Fig. 16): {Path(model.directory).name}", fontsize=9)
    _save(fig, out, data)
    return data


PHOTON_TYPES = ("A320neo", "F-16C Fighting Falcon", "Mavic 3")
PHOTON_SENSORS = ("1064nm-night", "1550nm-night")


def fig_photons(out, types=PHOTON_TYPES, sensors=PHOTON_SENSORS, poses: int = 6,
                seed: int = 0, lidar=None) -> dict:
    """What a single-photon lidar records (SPEC section 8, issue "Photons"): for a few types
    and the two example systems, against range, the detection probability (the share of the
    cells the target covers that report a signal point) and the points per cloud; and for
    the 1550 nm system, the share of noise points against the background rate. Each point of
    a curve averages ``poses`` random Table-1 attitudes (seeded). ``lidar``: the paper's
    when None."""
    import dataclasses

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.sensor import load_sensor, photon_cloud, reflectivity_of
    from dataset_builder.simulate import Simulator

    cat = default_catalog()
    rng = np.random.default_rng(seed)
    sim = (Simulator("embree", supersample=4) if lidar is None
           else Simulator("embree", lidar, supersample=4))
    deg = np.pi / 180

    def table(t, ranges):
        n = len(ranges) * poses
        r = np.repeat(ranges, poses)
        return np.stack([np.full(n, t.index), r, rng.uniform(3, 4, n) * deg,
                         rng.uniform(1, 5, n) * deg, rng.uniform(-60, 60, n) * deg,
                         rng.uniform(-5, 5, n) * deg], 1)

    curves = []
    for name in types:
        t = cat.get(name)
        ranges = (np.linspace(100, 600, 6) if t.range_band == "near"
                  else np.linspace(3000, 18000, 6))
        tab = table(t, ranges)
        hits = sim.sub_ray_hits(cat.mesh(t), tab, ("type", t.index))
        n_cells = sim.lidar.width * sim.lidar.height  # a cell's index in its window, per sample
        cell = (hits.h.astype(np.int64) - sim.lidar.h_min) * sim.lidar.width \
            + (hits.w.astype(np.int64) - sim.lidar.w_min)
        covered = np.bincount(np.unique(hits.sample * n_cells + cell) // n_cells,
                              minlength=len(tab))
        for s_name in sensors:
            sensor = load_sensor(s_name)
            pc = photon_cloud(hits, tab[:, 1], np.full(len(tab), reflectivity_of(t)), sensor,
                              sim.lidar, seed)
            sig = np.bincount(pc.sample, weights=pc.label, minlength=len(tab))
            pts = np.bincount(pc.sample, minlength=len(tab))
            pd = np.where(covered > 0, sig / np.maximum(covered, 1), np.nan)
            curves.append({"type": name, "sensor": s_name, "range_m": ranges.tolist(),
                           "detection_probability": np.nanmean(pd.reshape(-1, poses), 1)
                           .tolist(),
                           "points_per_cloud": pts.reshape(-1, poses).mean(1).tolist(),
                           "signal_points_per_cloud": sig.reshape(-1, poses).mean(1).tolist(),
                           "covered_cells": covered.reshape(-1, poses).mean(1).tolist()})
    # noise share against the background, the 1550 nm system, an A320neo at 6 km
    base = load_sensor("1550nm-night")
    t = cat.get(types[0])
    tab = table(t, np.array([6000.0]))
    hits = sim.sub_ray_hits(cat.mesh(t), tab, ("type", t.index))
    rates = np.logspace(3, 7, 9)
    share = []
    for rate in rates:
        s = dataclasses.replace(base, background_hz=float(rate))
        pc = photon_cloud(hits, tab[:, 1], np.full(len(tab), reflectivity_of(t)), s,
                          sim.lidar, seed)
        share.append(float((pc.label == 0).sum() / max(len(pc.label), 1)))
    sim.close()
    data = {"figure": "photons", "seed": seed, "poses_per_range": poses,
            "lidar": sim.lidar.to_dict(),
            "sensors": {s: dataclasses.asdict(load_sensor(s)) for s in sensors},
            "curves": curves,
            "noise_share": {"type": types[0], "range_m": 6000.0, "sensor": "1550nm-night",
                            "threshold": base.threshold, "background_hz": rates.tolist(),
                            "noise_share": share}}
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), constrained_layout=True)
    styles = {s: st for s, st in zip(sensors, ("-", "--", ":"), strict=False)}
    for c in curves:
        km = np.asarray(c["range_m"]) / 1000
        label = f"{c['type']}, {c['sensor']}"
        axes[0].plot(km, c["detection_probability"], "o" + styles[c["sensor"]], label=label)
        axes[1].plot(km, c["points_per_cloud"], "o" + styles[c["sensor"]], label=label)
    for ax, ylabel in zip(axes[:2], ("detection probability per covered cell",
                                     "points per cloud"), strict=True):
        ax.set_xscale("log")
        ax.set_xlabel("range (km)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[1].set_yscale("log")
    axes[0].legend(fontsize=7)
    axes[2].semilogx(rates, share, "o-")
    axes[2].set_xlabel("background count rate (Hz)")
    axes[2].set_ylabel("noise share of the points")
    axes[2].set_title(f"{types[0]} at 6 km, 1550 nm, threshold {base.threshold}")
    axes[2].grid(alpha=0.3)
    fig.suptitle("What a single-photon lidar records (100 pulses a cell, points output)")
    _save(fig, out, data)
    return data
