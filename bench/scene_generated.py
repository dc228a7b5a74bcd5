"""Generated, not only simulated (issue 36, part 5): the speed and the error of drawing a
scene's targets with a model (the shipped APCG+ by default) instead of the simulator.

    .venv/bin/python bench/scene_generated.py [--scene bench/scene_generated.toml]
        [--model default|DIR] [--repeats 5] [--json bench/results/scene_generated.json]

The scene (every target inside the model's condition space in every frame) is scanned in one
process, frame by frame, every target simulated (embree, as `apcg scene sequence`) and every
target generated (as `apcg scene sequence --generator MODEL`); once with the file's [scan]
(rows: a moving target has another pose in every row, so one drawing per row it reaches) and
once as a flash (one pose per target and frame, one drawing).

Time: wall and CPU ms per frame of ``SceneScanner.scan`` (no file written), the two scanners
alternated ``--repeats`` times after a warm-up frame each (the ray caster's mesh cache, the
model's session); medians, and the ratio simulated / generated taken run by run.

Error, per target, frame by frame: its points in the generated scene against its points in
the simulated scene, with the evaluation protocol's pair scores (training/scores.py: MMD, JSD,
Chamfer in m^2, the point-count ratio generated / simulated) and the cells both hold; the same
for the target scanned alone at the same poses (the model's own error, without occlusion),
so that what the scene adds shows; and each target's visible share (its points in the scene
over its points alone), simulated and generated. For reference, the model's own evaluation
(its evaluation.json: the held-out split, isolated targets at the window's centre) in the
bands of the scene's ranges, with the simulator's floor.

Where it could pay: one target alone, a flash, at the ends and the middle of the model's
ranges (a large and a medium airliner, a drone), ms per scan both ways (``--repeats`` x 10
scans each, alternated, medians).
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import shlex
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.scene import scene_from_dict  # noqa: E402
from dataset_builder.scene import SceneScanner  # noqa: E402
from training import scores  # noqa: E402

HERE = Path(__file__).resolve().parent
BANDS = ("aircraft 3-6 km", "aircraft 6-9 km")
SWEEP = (("A380-800", (3000.0, 6000.0, 12000.0, 18000.0)),
         ("A320neo", (3000.0, 6000.0, 12000.0, 18000.0)),
         ("Matrice 300 RTK", (100.0, 300.0, 600.0)))


def cells(scan, tid: int) -> dict:
    m = scan.instance == tid
    c = scan.cloud
    return {(int(w), int(h)): float(r)
            for w, h, r in zip(c.cell_w[m], c.cell_h[m], c.range_m[m], strict=True)}


def compare(sim_scans, gen_scans, tid: int, seed: int = 0) -> dict:
    """Target ``tid``'s generated points against its simulated ones, frame by frame."""
    rows, shared, only_sim, only_gen, dr = [], 0, 0, 0, []
    for f, (s, g) in enumerate(zip(sim_scans, gen_scans, strict=True)):
        a, b = s.cloud.xyz[s.instance == tid], g.cloud.xyz[g.instance == tid]
        if len(a) == 0 and len(b) == 0:
            continue
        rows.append(scores.score_pair(a, b, seed + 1000 * f + tid))
        ca, cb = cells(s, tid), cells(g, tid)
        both = set(ca) & set(cb)
        shared += len(both)
        only_sim += len(set(ca) - both)
        only_gen += len(set(cb) - both)
        dr += [abs(ca[k] - cb[k]) for k in both]
    out = scores.summarise(rows)
    out["cells"] = {"shared": shared, "simulated_only": only_sim, "generated_only": only_gen,
                    "iou": round(shared / max(1, shared + only_sim + only_gen), 4),
                    "median_abs_range_diff_m": round(float(np.median(dr)), 3) if dr else None}
    return out


def scanners(doc: dict, base: Path, model: str):
    return (SceneScanner(scene_from_dict(doc, "bench scene", base)),
            SceneScanner(scene_from_dict(doc, "bench scene", base, generator=model)))


def measure(doc: dict, base: Path, model: str, repeats: int, seed: int) -> dict:
    """One scene (``doc``): time per frame both ways, and each target's error."""
    sim, gen = scanners(doc, base, model)
    frames = list(range(sim.scene.frames))
    n = len(sim.scene.targets)
    wall, cpu, scans = {"simulated": [], "generated": []}, {"simulated": [],
                                                           "generated": []}, {}
    try:
        sim.scan(0), gen.scan(0)  # warm-up: mesh caches, the model's session
        for _ in range(repeats):  # alternated: a drifting machine moves both
            for name, sc in (("simulated", sim), ("generated", gen)):
                t0, c0 = time.perf_counter(), time.process_time()
                scans[name] = [sc.scan(f) for f in frames]
                wall[name].append(1e3 * (time.perf_counter() - t0) / len(frames))
                cpu[name].append(1e3 * (time.process_time() - c0) / len(frames))
        drawings = 0
        for f in frames:  # the network's conditions a frame: distinct poses drawn
            for i in range(n):
                if gen.scene.targets[i].generator is not None:
                    *_, groups = gen._geometry(i, float(gen.scene.frame_times([f])[0]))
                    drawings += len(groups) if len(groups) else 0
    finally:
        sim.close()
        gen.close()

    def med(v):
        return round(float(np.median(v)), 3)

    out = {"scan": doc.get("scan", {"pattern": "flash"}), "frames": len(frames),
           "fallback_target_frames": sum(len(s.fallback) for s in scans["generated"]),
           "row_groups_drawn_per_frame": round(drawings / len(frames), 2),
           "ms_per_frame": {
               name: {"wall_median": med(wall[name]), "cpu_median": med(cpu[name]),
                      "wall_runs": [round(x, 3) for x in wall[name]]}
               for name in ("simulated", "generated")},
           "speedup_simulated_over_generated": {
               "wall_median": med(np.array(wall["simulated"]) / np.array(wall["generated"])),
               "cpu_median": med(np.array(cpu["simulated"]) / np.array(cpu["generated"]))},
           "targets": {}}
    for i, t in enumerate(sim.scene.targets, start=1):
        one = copy.deepcopy(doc)
        one["target"] = [copy.deepcopy(doc["target"][i - 1])]
        a_sim, a_gen = scanners(one, base, model)
        try:
            s_alone = [a_sim.scan(f) for f in frames]
            g_alone = [a_gen.scan(f) for f in frames]
        finally:
            a_sim.close()
            a_gen.close()

        def share(scene_scans, alone_scans, tid=i):
            seen = sum(int((s.instance == tid).sum()) for s in scene_scans)
            return round(seen / max(1, sum(len(s.cloud) for s in alone_scans)), 4)

        out["targets"][str(i)] = {
            "type": t.type_name,
            "in_scene": compare(scans["simulated"], scans["generated"], i, seed),
            "alone": compare(s_alone, g_alone, 1, seed),
            "visible_share": {"simulated": share(scans["simulated"], s_alone),
                              "generated": share(scans["generated"], g_alone)}}
    return out


def sweep(model: str, repeats: int) -> list[dict]:
    """One target alone (pitch 3, yaw 30 deg, elevation 3.5 deg), a flash: ms per scan."""
    out = []
    for type_name, ranges in SWEEP:
        for r in ranges:
            doc = {"target": [{"type": type_name, "range_m": r, "elevation_deg": 3.5,
                               "pitch_deg": 3.0, "yaw_deg": 30.0}]}
            sim, gen = scanners(doc, HERE, model)
            ms = {"simulated": [], "generated": []}
            points = {}
            try:
                sim.scan(0), gen.scan(0)
                for _ in range(repeats):
                    for name, sc in (("simulated", sim), ("generated", gen)):
                        t0 = time.perf_counter()
                        for _ in range(10):
                            points[name] = len(sc.scan(0).cloud)
                        ms[name].append(1e2 * (time.perf_counter() - t0))
            finally:
                sim.close()
                gen.close()
            out.append({"type": type_name, "range_m": r, "points": points,
                        "ms_simulated": round(float(np.median(ms["simulated"])), 3),
                        "ms_generated": round(float(np.median(ms["generated"])), 3),
                        "speedup_simulated_over_generated": round(float(np.median(
                            np.array(ms["simulated"]) / np.array(ms["generated"]))), 3)})
    return out


def main() -> int:
    from bench_output import emit

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default=str(HERE / "scene_generated.toml"))
    ap.add_argument("--model", default="default",
                    help='the generator: "default" (the shipped model) or a model directory')
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json")
    args = ap.parse_args()

    path = Path(args.scene).resolve()
    doc = tomllib.loads(path.read_text())
    flash = {k: v for k, v in doc.items() if k != "scan"}
    runs = {"file_scan": measure(doc, path.parent, args.model, args.repeats, args.seed),
            "flash": measure(flash, path.parent, args.model, args.repeats, args.seed)}

    from apcg_core.families import load_model
    model = load_model(None if args.model == "default" else args.model)
    reference = {}
    ev = model.directory / "evaluation.json"
    if ev.is_file():
        bands = json.loads(ev.read_text()).get("bands", {})
        for band in BANDS:
            b = bands.get(band)
            if b:
                floor = b.get("floor") or {}
                reference[band] = {"mmd": b.get("mmd"), "chamfer_m2": b.get("chamfer_m2"),
                                   "points_ratio_p10_p50_p90": b.get(
                                       "points_ratio_p10_p50_p90"),
                                   "floor_mmd": floor.get("mmd"),
                                   "floor_chamfer_m2": floor.get("chamfer_m2")}
    scene_name = str(path.relative_to(HERE.parent)) if path.is_relative_to(HERE.parent) \
        else str(path)
    report = {"command": "python bench/scene_generated.py " + shlex.join(sys.argv[1:]),
              "machine": {"cpus": os.cpu_count(),
                          "APCG_THREADS": os.environ.get("APCG_THREADS")},
              "scene": scene_name, "model": args.model, "repeats": args.repeats,
              "runs": runs, "one_target_flash": sweep(args.model, args.repeats),
              "model_evaluation_for_reference": reference}
    emit(report, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
