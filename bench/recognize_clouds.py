"""Where the default model loses recognition accuracy, seen in the clouds (issue 35, point 4).

For the benchmark's default types at random Table 1 conditions (the benchmark's own condition
plan and sources, training.recognize), the exact cloud and the default model's cloud of each
condition: mean point count and mean extent per axis (observation frame: x across the line of
sight, y up, z along it) per type and range group, and a picture of the look-alike pairs at one
near condition, exact beside generated.

    .venv/bin/python bench/recognize_clouds.py --per-type 40 \
        --plot docs/evaluation/recognize/clouds.png --json bench/results/recognize_clouds.json \
        [--model DIR] [--force]

``--model``: another model directory in place of the shipped default (a candidate).

An existing --plot file stops the run before any work unless ``--force``
(``bench_output.refuse``); the --json result is replaced in place, as every bench's is.
"""

from __future__ import annotations

import argparse

import numpy as np

from apcg_core.depth import DEFAULT_LIDAR
from apcg_core.families import default_model_dir
from training import recognize as R


def group(band: str) -> str:
    if band.startswith("drone"):
        return "drone"
    lo = float(band.split()[1].split("-")[0])
    return "3-6 km" if lo < 6 else ("6-12 km" if lo < 12 else "12-18 km")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--per-type", type=int, default=40)
    ap.add_argument("--seed", type=int, default=12345)
    ap.add_argument("--plot")
    ap.add_argument("--json")
    ap.add_argument("--force", action="store_true", help="replace the --plot file")
    ap.add_argument("--model", default=None, help="model directory (default: the shipped one)")
    a = ap.parse_args()
    from bench_output import emit, refuse, save_figure
    refuse([a.plot], a.force)
    types = list(R.DEFAULT_TYPES)
    tab = R.conditions(types, a.per_type, a.seed)
    exact, _ = R.simulated("embree", 1, types, tab, None, DEFAULT_LIDAR, 0)
    gen, _ = R.Source(a.model or str(default_model_dir())).clouds(types, tab, 0)
    bands = R.bands_of(types, tab)
    rows: dict = {}
    for i, (e, g) in enumerate(zip(exact, gen, strict=True)):
        if len(e) < 2 or len(g) < 2:
            continue
        key = f"{types[int(tab[i, 0])]} | {group(bands[i])}"
        rows.setdefault(key, []).append([len(e), len(g), *np.ptp(e, 0), *np.ptp(g, 0)])
    table = {}
    print("type | range | n | points exact / generated | extent x, y, z exact | generated (m)")
    for key, v in rows.items():
        m = np.mean(v, axis=0)
        table[key] = {"n": len(v), "points": [round(m[0], 1), round(m[1], 1)],
                      "extent_exact_m": np.round(m[2:5], 2).tolist(),
                      "extent_generated_m": np.round(m[5:8], 2).tolist()}
        print(f"{key} | {len(v)} | {m[0]:.0f} / {m[1]:.0f} | {m[2]:.1f} {m[3]:.1f} {m[4]:.1f} | "
              f"{m[5]:.1f} {m[6]:.1f} {m[7]:.1f}")
    if a.json:  # the same bytes as before: indented JSON and a newline
        emit({"per_type": a.per_type, "seed": a.seed, "groups": table}
             | ({"model": a.model} if a.model else {}), a.json, show=False)
    if a.plot:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        names = [n for pair in R.LOOK_ALIKE for n in pair]
        fig, axes = plt.subplots(2, len(names), figsize=(4 * len(names), 4.0),
                                 constrained_layout=True)
        for j, name in enumerate(names):
            code = types.index(name)
            # the type's first condition in the near band; with few conditions a type may have
            # none there, and then its nearest one is drawn (the panel says its range)
            own = [i for i in range(len(tab)) if int(tab[i, 0]) == code]
            near = [i for i in own if bands[i] == "aircraft 3-6 km"]
            i = near[0] if near else min(own, key=lambda i: tab[i, 1])
            for row, (what, clouds) in enumerate((("exact", exact), ("APCG+ default", gen))):
                c = clouds[i] - np.median(exact[i], 0)
                ax = axes[row, j]
                ax.scatter(c[:, 0], c[:, 1], s=2, c=c[:, 2], cmap="viridis")
                ax.set_aspect("equal")
                ax.set_xlim(-24, 24)
                ax.set_ylim(-8, 8)
                ax.set_title(f"{name} {what}: {len(c)} points, {np.ptp(c[:, 0]):.1f} m wide",
                             fontsize=9)
                ax.grid(alpha=0.3)
            axes[1, j].set_xlabel(f"x (m) at {tab[i, 1] / 1000:.1f} km, yaw "
                                  f"{np.degrees(tab[i, 4]):.0f} deg")
        save_figure(fig, a.plot, dpi=90)


if __name__ == "__main__":
    main()
