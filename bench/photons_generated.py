"""Photons from the generator (issue 33, point 3): `apcg generate --sensor X` feeds the same
photon stage as `apcg simulate --sensor X` (SPEC section 8, "Generated clouds"). Clouds are
random now, so the comparison is distributional, per band: signal points per cloud, the noise
share, and MMD between the generated-with-photons cloud and a simulated-with-photons draw,
against the floor of two simulated draws of the same condition (other seeds).

    .venv/bin/python bench/photons_generated.py -o docs/evaluation/lidars \
        [--sensors 1550nm-night,1550nm-day] [--per-band 6] [--seed 0] [--model DIR] [--force]

Conditions: per band, --per-band random built-in types of that band at random Table 1
conditions (seeded). Simulated: embree, 4 x 4 sub-rays per cell (simulate's default with a
sensor), draws seeded (seed + 1, id) and (seed + 2, id); generated: the shipped default model
(or ``--model``), its photons seeded (seed + 3, id): no two of the three share a draw. MMD by
the protocol's settings (2,048 points at most).
Writes OUT/photons_generated.json and OUT/photons_generated.md; when either exists the run
stops before any work unless ``--force`` (``bench_output.refuse``).
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

from apcg_core.catalog.catalog import default_catalog  # noqa: E402
from apcg_core.families import load_model  # noqa: E402
from apcg_core.lidar import DEG  # noqa: E402
from apcg_core.metrics import mmd  # noqa: E402
from apcg_core.sensor import load_sensor, to_cloud  # noqa: E402
from apcg_core.sensor.generated import photon_generated  # noqa: E402
from dataset_builder.simulate import Simulator  # noqa: E402
from training.scores import BANDS_M, MAX_POINTS, band_of, band_order  # noqa: E402


def conditions(model, per_band: int, seed: int):
    """(names, table) with ``per_band`` conditions in each Table 1 band."""
    rng = np.random.default_rng([seed, 33])
    cat = default_catalog()
    builtin = [t for t in cat if t.source == "builtin" and t.name in model.types]
    names, rows = [], []
    for kind, edges in BANDS_M.items():
        near = kind == "drone"
        pool = [t for t in builtin if (t.range_band == "near") == near]
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            for _ in range(per_band):
                t = pool[rng.integers(len(pool))]
                rows.append((0, rng.uniform(lo, min(hi, edges[-1] - 1e-3)),
                             rng.uniform(3, 4) * DEG, rng.uniform(1, 5) * DEG,
                             rng.uniform(-60, 60) * DEG, rng.uniform(-5, 5) * DEG))
                names.append(t.name)
    return names, np.array(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--sensors", default="1550nm-night,1550nm-day")
    ap.add_argument("--per-band", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cell-reads", action="store_true",
                    help="one return per generated point filling its cell (K = 1), not the "
                         "model's 3 x 3 sub-reads")
    ap.add_argument("--model", default=None, help="a model directory (default: the shipped "
                    "default); its incidence output is used where it has one (SPEC section 8)")
    ap.add_argument("--force", action="store_true",
                    help="replace OUT/photons_generated.json and .md when they exist")
    args = ap.parse_args()
    from bench_output import refuse, write_text
    report = [Path(args.output) / "photons_generated.json",
              Path(args.output) / "photons_generated.md"]
    refuse(report, args.force)
    model = load_model(args.model)
    cat = default_catalog()
    names, table = conditions(model, args.per_band, args.seed)
    cond = model.conditions(names, table[:, 1:])
    res = model.generate(cond)
    gen_table = res.table
    out = {"command": "python bench/photons_generated.py " + shlex.join(sys.argv[1:]),
           "generated_photons": "cell reads (K = 1)" if args.cell_reads else "3 x 3 sub-reads",
           "model": str(model.directory), "per_band": args.per_band, "seed": args.seed,
           "sensors": {}}
    for sname in args.sensors.split(","):
        sensor = load_sensor(sname)
        t0 = time.perf_counter()
        gen = photon_generated(res.cloud, gen_table, names, model.lidar, sensor,
                               args.seed + 3, 0, model=None if args.cell_reads else model)
        draws = []
        with Simulator("embree", model.lidar, supersample=4) as sim:
            for k in (1, 2):
                parts = []
                for i, name in enumerate(names):
                    cells, _, _ = sim.photon_cells_type(cat, name, table[i:i + 1], sensor,
                                                        args.seed + k, np.array([i]))
                    c = to_cloud(cells, table[i:i + 1, 2], model.lidar)
                    parts.append(c)
                draws.append(parts)
        rows = {}
        for i, name in enumerate(names):
            near = cat.get(name).range_band == "near"
            band = band_of(table[i, 1], near)
            g = gen.sample == i
            a, b = draws[0][i], draws[1][i]
            row = rows.setdefault(band, {"sim_signal": [], "gen_signal": [], "sim_noise": [],
                                         "gen_noise": [], "mmd_gen": [], "mmd_floor": []})
            row["sim_signal"].append(int((a.label == 1).sum()))
            row["gen_signal"].append(int((gen.label[g] == 1).sum()))
            row["sim_noise"].append(float((a.label == 0).mean()) if len(a) else None)
            row["gen_noise"].append(float((gen.label[g] == 0).mean()) if g.any() else None)
            row["mmd_gen"].append(mmd(a.xyz, gen.xyz[g], max_points=MAX_POINTS, seed=i))
            row["mmd_floor"].append(mmd(a.xyz, b.xyz, max_points=MAX_POINTS, seed=i))

        def mean(v):
            v = [x for x in v if x is not None]
            return float(np.mean(v)) if v else None
        summary = {band: {k: mean(v) for k, v in r.items()} | {"conditions": len(r["sim_signal"])}
                   for band, r in sorted(rows.items(), key=lambda kv: band_order(kv[0]))}
        out["sensors"][sname] = {"bands": summary, "seconds": round(time.perf_counter() - t0, 1)}
    Path(args.output).mkdir(parents=True, exist_ok=True)
    write_text(report[0], json.dumps(out, indent=1) + "\n")
    text = markdown(out)
    write_text(report[1], text)
    print(text)
    return 0


def markdown(out: dict) -> str:
    def f(v, fmt):
        return "-" if v is None else fmt.format(v)
    lines = ["| sensor | band | conditions | signal points: simulated | generated | noise share: "
             "simulated | generated | MMD generated vs simulated | floor: two simulated draws |",
             "|---|---|---|---|---|---|---|---|---|"]
    for sname, s in out["sensors"].items():
        for band, b in s["bands"].items():
            lines.append(f"| {sname} | {band} | {b['conditions']} | "
                         f"{f(b['sim_signal'], '{:.1f}')} | {f(b['gen_signal'], '{:.1f}')} | "
                         f"{f(b['sim_noise'], '{:.2f}')} | {f(b['gen_noise'], '{:.2f}')} | "
                         f"{f(b['mmd_gen'], '{:.4f}')} | {f(b['mmd_floor'], '{:.4f}')} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
