"""What the photon stage (issue "Photons", SPEC section 8) costs beside the embree simulation
of the same clouds, in one run.

    .venv/bin/python bench/photons.py [--samples-per-type 40] [--rounds 3]
        [--sensors 1550nm-day,1550nm-night] [--json out.json] [--bright-counts 3]

Random Table-1 conditions for the demo config's six types (four aircraft at 3-18 km, two drones
at 100-600 m), the same for every row. Each round times, per type batch:

* ``ideal_k4``: the ideal standard clouds at 4 x 4 rays per cell (``simulate_cells``), the
  embree simulation of the same cells and rays the sensor sees;
* ``ideal_k1``: the default ideal clouds (one ray per cell), for scale;
* ``hits_k4``: ``sub_ray_hits``: the same rays, each hit's range and incidence (the geometry
  the stage needs; one embree intersection query);
* ``stage[SENSOR]``: ``photon_cloud`` on those hits (points output, the preset's 100 pulses).

Figures: the median over rounds of each, and the ratios stage / ideal_k4 (what the stage adds)
and (hits_k4 + stage) / ideal_k4 (the whole photon cloud against the ideal one at K = 4).
Times are CPU seconds of the process by default (`--clock wall` for wall clock).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.catalog.catalog import default_catalog  # noqa: E402
from apcg_core.depth import DEFAULT_LIDAR  # noqa: E402
from apcg_core.sensor import load_sensor, photon_cloud, points, reflectivity_of  # noqa: E402
from dataset_builder.simulate import Simulator  # noqa: E402

# CPU seconds of this process (every thread): on a shared machine the ratios of CPU time hold
# where wall-clock ratios drift with the load; --clock wall for wall-clock seconds
CLOCK = time.process_time

TYPES = ["A320neo", "777-300ER", "F-16C Fighting Falcon", "UH-60 Black Hawk",
         "Matrice 300 RTK", "Mavic 3"]
DEG = np.pi / 180


def conditions(catalog, per_type: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    out = {}
    for name in TYPES:
        t = catalog.get(name)
        lo, hi = (100.0, 600.0) if t.range_band == "near" else (3000.0, 18000.0)
        n = per_type
        out[name] = np.stack([np.full(n, t.index), rng.uniform(lo, hi, n),
                              rng.uniform(3, 4, n) * DEG, rng.uniform(1, 5, n) * DEG,
                              rng.uniform(-60, 60, n) * DEG, rng.uniform(-5, 5, n) * DEG], 1)
    return out


def one_round(catalog, conds: dict, sensors: dict, sims: dict) -> dict:
    times = {"ideal_k1": 0.0, "ideal_k4": 0.0, "hits_k4": 0.0,
             **{f"stage[{s}]": 0.0 for s in sensors}}
    n_points = {s: 0 for s in sensors}
    for name, table in conds.items():
        t = catalog.get(name)
        mesh = catalog.mesh(t)
        key = ("type", t.index)
        for label, sim in (("ideal_k1", sims[1]), ("ideal_k4", sims[4])):
            t0 = CLOCK()
            sim.simulate_cells(mesh, table, key)
            times[label] += CLOCK() - t0
        t0 = CLOCK()
        hits = sims[4].sub_ray_hits(mesh, table, key)
        times["hits_k4"] += CLOCK() - t0
        rho = np.full(len(table), reflectivity_of(t))
        for s, sensor in sensors.items():
            t0 = CLOCK()
            pc = photon_cloud(hits, table[:, 1], rho, sensor, DEFAULT_LIDAR, seed=1)
            times[f"stage[{s}]"] += CLOCK() - t0
            n_points[s] += len(pc.range_m)
    return {"seconds": times, "points": n_points}


def main() -> int:
    from bench_output import emit

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples-per-type", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--sensors", default="1550nm-day,1550nm-night")
    ap.add_argument("--clock", choices=("cpu", "wall"), default="cpu",
                    help="what is timed: this process's CPU seconds (default) or wall clock")
    ap.add_argument("--json", help="write the result here too")
    ap.add_argument("--bright-counts", type=float,
                    help="points.BRIGHT_COUNTS for this run (how the stage's cost moves with "
                         "the split of a loud cell into pieces; the output's law is the same)")
    args = ap.parse_args()
    if args.bright_counts is not None:
        points.BRIGHT_COUNTS = args.bright_counts
    global CLOCK
    CLOCK = time.process_time if args.clock == "cpu" else time.perf_counter
    catalog = default_catalog()
    conds = conditions(catalog, args.samples_per_type)
    sensors = {s: load_sensor(s) for s in args.sensors.split(",")}
    sims = {1: Simulator("embree"), 4: Simulator("embree", supersample=4)}
    one_round(catalog, {k: v[:2] for k, v in conds.items()}, sensors, sims)  # warm-up
    rounds = [one_round(catalog, conds, sensors, sims) for _ in range(args.rounds)]
    med = {k: float(np.median([r["seconds"][k] for r in rounds])) for k in rounds[0]["seconds"]}
    ratios = {}
    for s in sensors:
        stage = np.array([r["seconds"][f"stage[{s}]"] for r in rounds])
        ideal = np.array([r["seconds"]["ideal_k4"] for r in rounds])
        hits = np.array([r["seconds"]["hits_k4"] for r in rounds])
        ratios[s] = {"stage_over_ideal_k4": round(float(np.median(stage / ideal)), 3),
                     "photon_cloud_over_ideal_k4": round(float(np.median((hits + stage)
                                                                         / ideal)), 3)}
    n = args.samples_per_type * len(TYPES)
    emit({"command": "python bench/photons.py " + shlex.join(sys.argv[1:]),
          "machine": {"cpus": os.cpu_count()}, "clock": args.clock, "samples": n, "types": TYPES,
          "rounds": args.rounds, "bright_counts": points.BRIGHT_COUNTS,
          "median_seconds": {k: round(v, 4) for k, v in med.items()},
          "ms_per_sample": {k: round(1e3 * v / n, 3) for k, v in med.items()},
          "ratios": ratios, "points_per_sample": {s: round(rounds[0]["points"][s] / n, 1)
                                                  for s in sensors}}, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
