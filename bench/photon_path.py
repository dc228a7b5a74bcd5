"""How well the photon stage's path for generated clouds reproduces the signal the simulator's
sub-rays give (issue 35: where photon clouds from the generator lose recognition).

The exact simulator's photon stage lights each cell with 4 x 4 sub-rays and reads each one's
incidence off the mesh's face normal. A family that draws at any lidar gives the stage 3 x 3
sub-rays instead, drawn at the 3-times finer lidar, their incidence read off the range slope
(``apcg_core.sensor.generated``). Per cell, the expected signal photo-electrons per pulse E
(``apcg_core.sensor.link.signal_photoelectrons``, summed over the cell's sub-rays) of:

* ``exact 3x3``: the simulator's 3 x 3 sub-rays with true normals (the sub-ray count alone);
* ``path on exact``: the simulator's clouds at the finer lidar read as the generated path reads
  a model's (``sub_rays_of_fine_cloud``): the path alone, on perfect geometry;
* ``path on exact, previous rule`` (``--previous``): the same with the rule before stop 46
  (centred differences across one whole cell, 3 finer cells);
* each ``--model``: the path on the model's own draw (``sub_ray_hits``), as
  ``apcg generate --sensor`` and the recognition benchmark do (its incidence output where it
  has one); with ``--slope``, also the same draw with the incidence read off the range's slope
  (the path of a model without an incidence output); with ``--true-cos``, also the same draw
  with each sub-ray's true cosine where the simulator's finer-cell ray meets the target in
  that finer cell (else the model's): what a perfect incidence output would give on the
  model's geometry.

against ``exact 4x4``, for the recognition benchmark's aircraft types at its test conditions
(``training.recognize.conditions``, ``--seed``) in one range band: cells lit by either, the
sum of E, the correlation of E over those cells, the mean absolute difference of
1 - exp(-pulses E) (the chance that a pulse train carries signal at all: what decides which
cells fire), and the sub-rays' mean cosine of incidence and share of grazing ones.

    .venv/bin/python bench/photon_path.py [--model apcg_core/models/default] [--slope] \
        [--true-cos] [--previous] [--sensor 1550nm-day] [--band 3000,6000] [--agree 4] \
        [--json bench/results/photon_path.json]
    .venv/bin/python bench/photon_path.py --model apcg_core/models/default \
        --show-row A320neo,4200,3.5,0.05,0.6,0.02      # one condition's ranges along a row
"""

from __future__ import annotations

import argparse
import copy

import numpy as np

from apcg_core.catalog import default_catalog
from apcg_core.depth import DEFAULT_LIDAR as LIDAR
from apcg_core.families import load_model
from apcg_core.sensor import generated as G
from apcg_core.sensor.link import signal_photoelectrons
from apcg_core.sensor.params import load_sensor
from apcg_core.sensor.reflectivity import reflectivity_of
from dataset_builder.simulate import Simulator
from training import recognize as R

AIRCRAFT = ("A320neo", "737-800", "G650ER", "G550", "777-300ER", "F-16C Fighting Falcon",
            "UH-60 Black Hawk")


class Lit(dict):
    """Cell key -> expected signal photo-electrons per pulse (summed over its sub-rays), and
    the sub-rays' incidence: their mean cosine and the share below :data:`GRAZING`."""

    def __init__(self, hits, rho: float, sensor) -> None:
        pe = signal_photoelectrons(hits.range_m, hits.cos, rho, sensor, hits.sub_rays)
        key = ((hits.sample.astype(np.int64) << 32)
               + ((hits.h.astype(np.int64) + (1 << 15)) << 16)
               + (hits.w.astype(np.int64) + (1 << 15)))
        u, inv = np.unique(key, return_inverse=True)
        super().__init__(zip(u.tolist(), np.bincount(inv, pe).tolist(), strict=True))
        self.mean_cos = float(hits.cos.mean()) if len(hits.cos) else None
        self.grazing = float((hits.cos < GRAZING).mean()) if len(hits.cos) else None


GRAZING = 0.3  # a sub-ray "grazing" below this cosine of incidence (about 73 degrees)


def compare(ref: Lit, got: Lit, pulses: int) -> dict:
    keys = sorted(set(ref) | set(got))
    x = np.array([ref.get(k, 0.0) for k in keys])
    y = np.array([got.get(k, 0.0) for k in keys])
    fire = np.abs(np.exp(-pulses * x) - np.exp(-pulses * y))
    return {"cells": int((y > 0).sum()), "cells_both": int(((x > 0) & (y > 0)).sum()),
            "sum_ratio": round(float(y.sum() / x.sum()), 4),
            "correlation": round(float(np.corrcoef(x, y)[0, 1]), 4),
            "fire_difference": round(float(fire.mean()), 4),
            "mean_cos": round(got.mean_cos, 3), "grazing_share": round(got.grazing, 3)}


def previous_rule_hits(cloud, elevation, lidar, n, k=G.SUB_READS):
    """The rule before stop 46: centred differences across one whole cell (k finer cells),
    one-sided at an edge, flat alone."""
    fine = G.sub_ray_lidar(lidar, k)
    s = np.asarray(cloud.sample, np.int64)
    w, h, r = cloud.cell_w.astype(np.int64), cloud.cell_h.astype(np.int64), cloud.range_m
    span = fine.width + 2 * k
    key = (s * (fine.height + 2 * k) + (h - fine.h_min + k)) * span + (w - fine.w_min + k)
    order = np.argsort(key, kind="stable")
    key, s, w, h, r = key[order], s[order], w[order], h[order], r[order]

    def slope(off):
        minus = G._neighbour_range(key, key, r, -off)
        plus = G._neighbour_range(key, key, r, off)
        return np.where(np.isfinite(minus) & np.isfinite(plus), (plus - minus) / 2.0,
                        np.where(np.isfinite(plus), plus - r,
                                 np.where(np.isfinite(minus), r - minus, 0.0))) / k
    beta = np.asarray(elevation, np.float64)[s] + h * fine.r_beta
    cos = 1.0 / np.sqrt(1.0 + (slope(k) / (r * fine.r_alpha * np.cos(beta))) ** 2
                        + (slope(k * span) / (r * fine.r_beta)) ** 2)
    return G.cells_of_fine_hits(G.SubRayHits(s, w.astype(np.int32), h.astype(np.int32), r,
                                             cos, n, 1), lidar, k)


def true_cos_hits(model, t, name, true):
    """``model``'s sub-rays of conditions ``t`` (its draw at the finer lidar), each with the
    cosine of the simulator's ray through the same finer cell (``true``: its sub-ray hits at
    the finer lidar, one ray a cell) where that ray meets the target, else the model's own."""
    own = G.fine_hits(model, t, [name] * len(t), LIDAR)

    def key(h):
        return ((h.sample.astype(np.int64) << 32) + ((h.h.astype(np.int64) + (1 << 15)) << 16)
                + (h.w.astype(np.int64) + (1 << 15)))

    k_true = key(true)
    order = np.argsort(k_true)
    k_true, cos_true = k_true[order], true.cos[order]
    k_own = key(own)
    at = np.minimum(np.searchsorted(k_true, k_own), len(k_true) - 1)
    found = k_true[at] == k_own
    own.cos[found] = cos_true[at[found]]
    return G.cells_of_fine_hits(own, LIDAR)


def show_row(spec: str, models) -> None:
    """Print the ranges (r - r0) along the fullest finer row of one condition, exact and each
    model's: TYPE,RANGE_M,ELEVATION_DEG,PITCH,YAW,ROLL (angles of the attitude in radians)."""
    name, *vals = spec.split(",")
    r0, elev, pitch, yaw, roll = (float(v) for v in vals)
    t = np.array([[0.0, r0, np.radians(elev), pitch, yaw, roll]])
    fine = G.sub_ray_lidar(LIDAR)
    with Simulator("embree", fine, quantize=False) as sim:
        clouds = {"exact": sim.simulate_type(default_catalog(), name, t).cloud}
    for m in models:
        m = G.sub_ray_model(m, LIDAR)
        clouds[str(m.directory)] = m.generate(m.conditions([name], t[:, 1:])).cloud
    ex = clouds["exact"]
    rows, counts = np.unique(ex.cell_h, return_counts=True)
    row = rows[np.argmax(counts)]
    mid = int(np.median(ex.cell_w[ex.cell_h == row]))
    print(f"finer row {row}, finer columns {mid - 20} .. {mid + 19}, r - r0 in m ('.': none):")
    for label, c in clouds.items():
        at = dict(zip(c.cell_w[c.cell_h == row].tolist(), c.range_m[c.cell_h == row] - r0,
                      strict=True))
        print(f"  {label}: " + " ".join(f"{at[w]:.2f}" if w in at else "."
                                         for w in range(mid - 20, mid + 20)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", action="append", default=[], help="a model directory whose "
                    "family draws at any lidar (repeatable)")
    ap.add_argument("--previous", action="store_true", help="also the rule before stop 46")
    ap.add_argument("--slope", action="store_true", help="also each model's draw with the "
                    "incidence from the range's slope, where it has an incidence output")
    ap.add_argument("--true-cos", action="store_true", help="also each model's draw with the "
                    "simulator's true cosines at its finer cells")
    ap.add_argument("--agree", type=float, default=G.AGREE, help="the slope rule's AGREE "
                    "(apcg_core.sensor.generated; default the package's)")
    ap.add_argument("--sensor", default="1550nm-day")
    ap.add_argument("--band", default="3000,6000", help="slant range band, metres: LO,HI")
    ap.add_argument("--test-per-type", type=int, default=R.TEST_PER_TYPE)
    ap.add_argument("--seed", type=int, default=0, help="the recognition benchmark's --seed")
    ap.add_argument("--show-row", metavar="TYPE,RANGE_M,ELEV_DEG,PITCH,YAW,ROLL",
                    help="only print one condition's ranges along a finer row, exact and "
                         "each --model's")
    ap.add_argument("--json")
    a = ap.parse_args()
    if a.show_row:
        show_row(a.show_row, [load_model(d) for d in a.model])
        return
    from bench_output import emit
    sensor = load_sensor(a.sensor)
    G.AGREE = a.agree
    lo, hi = (float(x) for x in a.band.split(","))
    types = list(R.DEFAULT_TYPES)
    table = R.conditions(types, a.test_per_type, R._seed(a.seed, R.TEST_CONDITIONS))
    table = table[(table[:, 1] >= lo) & (table[:, 1] < hi)]
    cat = default_catalog()
    models = [load_model(d) for d in a.model]
    rows = {}
    for name in AIRCRAFT:
        t = table[table[:, 0] == types.index(name)]
        if not len(t):
            continue
        rho = reflectivity_of(cat.get(name))
        mesh = cat.mesh(cat.get(name))
        with Simulator("embree", LIDAR, quantize=False, supersample=4) as sim:
            ref = Lit(sim.sub_ray_hits(mesh, t), rho, sensor)
        with Simulator("embree", LIDAR, quantize=False, supersample=3) as sim:
            got = {"exact 3x3": Lit(sim.sub_ray_hits(mesh, t), rho, sensor)}
        fine = G.sub_ray_lidar(LIDAR)
        with Simulator("embree", fine, quantize=False, supersample=1) as sim:
            cloud = sim.simulate_type(cat, name, t).cloud
            true = sim.sub_ray_hits(mesh, t) if a.true_cos else None
        got["path on exact"] = Lit(G.sub_rays_of_fine_cloud(cloud, t[:, 2], LIDAR, len(t)),
                                        rho, sensor)
        if a.previous:
            got["path on exact, previous rule"] = Lit(
                previous_rule_hits(cloud, t[:, 2], LIDAR, len(t)), rho, sensor)
        for m in models:
            m = copy.copy(m)
            m.use_lidar(LIDAR)
            got[f"path on {m.directory}"] = Lit(
                G.sub_ray_hits(m, t, [name] * len(t), LIDAR), rho, sensor)
            if a.true_cos:
                got[f"path on {m.directory}, true cosines"] = Lit(
                    true_cos_hits(m, t, name, true), rho, sensor)
            if a.slope and getattr(m, "draws_incidence", False):
                m.draws_incidence = False
                got[f"path on {m.directory}, slope"] = Lit(
                    G.sub_ray_hits(m, t, [name] * len(t), LIDAR), rho, sensor)
        rows[name] = {"clouds": int(len(t)), "cells_exact_4x4": len(ref),
                      "sum_exact_4x4": round(sum(ref.values()), 3),
                      "mean_cos_exact_4x4": round(ref.mean_cos, 3),
                      "grazing_share_exact_4x4": round(ref.grazing, 3),
                      **{k: compare(ref, v, sensor.pulses) for k, v in got.items()}}
        print(f"{name} ({len(t)} clouds, {len(ref)} cells lit by 4x4 sub-rays, mean cos "
              f"{ref.mean_cos:.3f}, grazing {ref.grazing:.2f}):")
        for k in got:
            c = rows[name][k]
            print(f"  {k}: sum {c['sum_ratio']:.3f} x, correlation {c['correlation']:.3f}, "
                  f"fire difference {c['fire_difference']:.3f}, mean cos {c['mean_cos']:.3f}, "
                  f"grazing {c['grazing_share']:.2f}")
    emit({"sensor": a.sensor, "band_m": [lo, hi], "seed": a.seed, "agree": a.agree,
          "slope": a.slope, "true_cos": a.true_cos,
          "test_per_type": a.test_per_type, "models": a.model, "types": rows}, a.json,
         show=False)


if __name__ == "__main__":
    main()
