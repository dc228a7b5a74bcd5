"""How a generated cloud's photons get their incidence: the slope baseline (SPEC section 8,
"Generated clouds"; ``apcg_core.sensor.generated.SLOPE_BASELINE``).

A generator draws no surface normals; the photon stage reads a generated sub-ray's incidence
off the range slope between neighbours. The expected signal of a cloud goes as the sum over its
sub-rays of cos(incidence) (the stage's rho cos / r^2 per sub-ray, rho and r shared), so this
bench compares that sum for the shipped model's 3 x 3 sub-reads against the simulator's 4 x 4
sub-rays (embree, the mesh's own normals) on the same conditions, per type and band, for each
slope baseline: one lidar cell ("cell", the stage before) and shares of the model's drawn
resolution (one sheet pixel for APCG+).

    .venv/bin/python bench/photon_incidence.py [--per-type 10] [--baselines 0.35,0.5,0.7] \
        [--json bench/results/photon_incidence.json] [--force]

Conditions: per (type, band), --per-type random Table 1 conditions in the band (seeded).
Prints per baseline the ratio generated / simulated of each (type, band) and the mean |log|
of the ratios (0: the generated photons expect the simulator's signal everywhere).
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_output import emit, refuse  # noqa: E402

from apcg_core.catalog.catalog import default_catalog  # noqa: E402
from apcg_core.families import load_model  # noqa: E402
from apcg_core.lidar import DEG  # noqa: E402
from apcg_core.sensor import generated as gen  # noqa: E402
from dataset_builder.simulate import Simulator  # noqa: E402

CASES = [  # (types, band in metres)
    (("A320neo", "777-300ER", "G650ER", "F-16C Fighting Falcon", "UH-60 Black Hawk"), (3000, 6000)),
    (("A320neo", "777-300ER", "G650ER", "F-16C Fighting Falcon", "UH-60 Black Hawk"), (9000, 12000)),
    (("Mavic 3", "Matrice 300 RTK", "eBee X"), (100, 600)),
]
SIM_SUB = 4  # the simulator's sub-rays per cell side with a sensor (apcg simulate --sensor)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-type", type=int, default=10)
    ap.add_argument("--baselines", default="0.35,0.5,0.7",
                    help="shares of the drawn resolution to try (beside one lidar cell)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json")
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args()
    refuse([a.json] if a.json else [], a.force)
    model, cat = load_model(), default_catalog()
    fine = gen.sub_ray_lidar(model.lidar)
    k = gen.SUB_READS
    shares = [float(x) for x in a.baselines.split(",")]
    rng = np.random.default_rng(a.seed)
    ratios: dict = {"cell": {}} | {str(f): {} for f in shares}
    sim = Simulator("embree", model.lidar, supersample=SIM_SUB)
    for types, (lo, hi) in CASES:
        for name in types:
            n = a.per_type
            pose = np.column_stack([rng.uniform(lo, hi, n), rng.uniform(3, 4, n) * DEG,
                                    rng.uniform(1, 5, n) * DEG, rng.uniform(-60, 60, n) * DEG,
                                    rng.uniform(-5, 5, n) * DEG])
            table = model.conditions([name] * n, pose).table
            t = cat.get(name)
            simulated = sim.sub_ray_hits(cat.mesh(t), np.column_stack([np.full(n, t.index),
                                                                       pose]), ("type", t.index))
            want = simulated.cos.sum() / SIM_SUB**2
            fine_model = copy.copy(model)
            fine_model.lidar, fine_model.quantize = fine, False
            cloud = fine_model.generate(fine_model.conditions([name] * n, pose)).cloud
            key = f"{name}, {lo / 1000:g}-{hi / 1000:g} km"
            res = model.drawn_resolution_m(table)
            for label in ratios:
                if label == "cell":
                    kw = kh = np.full(n, k)
                else:
                    base = float(label) * res
                    kw = np.maximum(1, np.rint(base / (table[:, 1] * fine.r_alpha
                                                       * np.cos(table[:, 2])))).astype(int)
                    kh = np.maximum(1, np.rint(base / (table[:, 1] * fine.r_beta))).astype(int)
                hits = gen.hits_of_cloud(cloud, table[:, 2], fine, n, stride=kw, stride_h=kh)
                ratios[label][key] = round(float(hits.cos.sum() / k**2 / want), 4)
            print(key, " ".join(f"{lab}: {v[key]:.2f}" for lab, v in ratios.items()), flush=True)
    summary = {lab: round(float(np.mean(np.abs(np.log(list(v.values()))))), 4)
               for lab, v in ratios.items()}
    print("mean |log ratio|:", summary)
    emit({"per_type": a.per_type, "seed": a.seed, "sim_sub_rays": SIM_SUB**2,
          "generated_sub_reads": k**2, "shipped_baseline": gen.SLOPE_BASELINE,
          "ratio_generated_over_simulated": ratios, "mean_abs_log_ratio": summary},
         a.json, show=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
