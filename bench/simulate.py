"""Simulator and dataset-build throughput per backend, on Table-1 conditions, in one run.

    .venv/bin/python bench/simulate.py [--per-type 40] [--workers 2] [--json out.json]

For a seeded, stratified subset of the paper-table1 plan (the same samples for every backend)
it runs the dataset builder's own shard pipeline (simulate -> depth -> shard file written and
fsynced) and reports samples/s and rays/s, beside the raw embree ray rate on exactly the same
rays (float32 arrays ready, the call alone: the bound), and extrapolates to the full 10^6-sample
build with ``--workers`` processes, I/O included, and its size on disk. It also reports how the
backends agree with embree (cells in common, largest range difference) on those samples.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.catalog.catalog import default_catalog  # noqa: E402
from apcg_core.io.dataset import Shard, shard_agreement  # noqa: E402
from dataset_builder.build import ShardTask, _task, close_simulators, run_task, worker_init  # noqa: E402
from dataset_builder.plan import ShardPlan, load_config, make_plan  # noqa: E402


def subset_tasks(plan, catalog, per_type: int, out: Path, backend: str, seed: int = 0):
    rng = np.random.default_rng(seed)
    codes = plan.table[:, 0].astype(np.int64)
    tasks = []
    for code in range(len(plan.types)):
        rows = np.sort(rng.choice(np.flatnonzero(codes == code), per_type, replace=False))
        sp = ShardPlan(code, "train", code, rows)
        t = _task(plan, catalog, sp, out)
        t.backend = backend
        t.path = str(out / f"{backend}-{code:03d}.npz")
        tasks.append(t)
    return tasks


def run_serial(tasks: list[ShardTask]) -> float:
    t0 = time.perf_counter()
    for t in tasks:
        run_task(t)
    close_simulators()
    return time.perf_counter() - t0


def run_pool(tasks: list[ShardTask], workers: int, per_process: int | None) -> float:
    import multiprocessing as mp
    ctx = mp.get_context("spawn")
    t0 = time.perf_counter()
    with ctx.Pool(workers, initializer=worker_init, maxtasksperchild=per_process) as pool:
        list(pool.imap_unordered(run_task, tasks))
    return time.perf_counter() - t0


def raw_embree_seconds(plan, catalog, tasks, block: int | None = None) -> tuple[float, int]:
    """Seconds of embree's call alone, and the ray count, on the float32 rays the simulator
    makes for these samples (made beforehand, untimed); in calls of ``block`` rays when given,
    as the pipeline makes them."""
    wall, _, rays = raw_embree_times(plan, catalog, tasks, block)
    return wall, rays


def raw_embree_times(plan, catalog, tasks, block: int | None = None) -> tuple[float, float, int]:
    """:func:`raw_embree_seconds` as (wall seconds, CPU seconds of this process, rays)."""
    from dataset_builder.backends.embree import EmbreeCaster
    from dataset_builder.rays import angular_boxes, bounding_radius, make_rays, sample_frames
    total_t, total_cpu, total_rays = 0.0, 0.0, 0
    for t in tasks:
        mesh = catalog.mesh(t.type_catalog_index)
        caster = EmbreeCaster(mesh)
        radius = bounding_radius(mesh.vertices)
        m, c = sample_frames(t.table)
        boxes = angular_boxes(mesh.vertices, t.table, plan.lidar, m, c)
        rays = make_rays(t.table, boxes, plan.lidar, m, c, radius)
        o = np.ascontiguousarray(rays.origin, np.float32)
        d = np.ascontiguousarray(rays.direction, np.float32)
        step = block or max(1, len(o))
        for i in range(0, len(o), step):
            dist = np.full(len(o[i:i + step]), rays.t_max, np.float32)
            c0, t0 = time.process_time(), time.perf_counter()
            caster._scene.run(o[i:i + step], d[i:i + step], dists=dist, query="DISTANCE")
            total_t += time.perf_counter() - t0
            total_cpu += time.process_time() - c0
        total_rays += len(o)
    return total_t, total_cpu, total_rays


def raw_embree_rate(plan, catalog, tasks) -> tuple[float, int]:
    """Rays/s of embree's call alone, on the rays the simulator makes for these samples."""
    seconds, rays = raw_embree_seconds(plan, catalog, tasks)
    return rays / seconds, rays


def agreement(ref_dir: Path, other_dir: Path, backend: str, n_tasks: int) -> dict:
    tot = {"cells_common": 0, "cells_either": 0, "ranges_within_tol": 0}
    worst = 0.0
    for code in range(n_tasks):
        g = shard_agreement(Shard.load(ref_dir / f"embree-{code:03d}.npz"),
                            Shard.load(other_dir / f"{backend}-{code:03d}.npz"))
        for k in tot:
            tot[k] += g[k]
        worst = max(worst, g["max_range_diff_m"])
    # With quantized ranges a hit within micrometres of a bin edge may land in the next bin.
    return {"cells_in_common": tot["cells_common"] / max(tot["cells_either"], 1),
            "ranges_within_2mm": tot["ranges_within_tol"] / max(tot["cells_common"], 1),
            "max_range_diff_m": worst}


def main() -> int:
    from bench_output import emit

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-type", type=int, default=40, help="samples per type (80 types)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--backends", default="embree,blender,points,blender-bvh")
    ap.add_argument("--bvh-per-type", type=int, default=5,
                    help="samples per type for the slow blender-bvh loop")
    ap.add_argument("--json", help="write the results here too")
    args = ap.parse_args()

    catalog = default_catalog()
    plan = make_plan(load_config("paper-table1"), catalog)
    n_full = plan.n_samples
    results = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
               "command": "python bench/simulate.py " + shlex.join(sys.argv[1:]),
               "backends": {}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for backend in args.backends.split(","):
            per = args.bvh_per_type if backend == "blender-bvh" else args.per_type
            out = tmp / (backend if per == args.per_type else backend + "-small")
            out.mkdir()
            if backend.startswith("blender"):
                import bpy
                bpy.ops.wm.read_factory_settings(use_empty=True)
            tasks = subset_tasks(plan, catalog, per, out, backend)
            n = sum(len(t.rows) for t in tasks)
            run_task(tasks[0])  # warm: imports, first caster
            serial = run_serial(tasks)
            shards = [Shard.load(t.path) for t in tasks]
            rays = int(sum(s.n_rays.astype(np.int64).sum() for s in shards))
            points = int(sum(len(s.pixel) for s in shards))
            size = sum(Path(t.path).stat().st_size for t in tasks)
            clamped = np.array([int(s.n_clamped.sum()) for s in shards])
            n_pts = np.array([len(s.pixel) for s in shards])
            worst = np.argsort(-clamped / np.maximum(n_pts, 1))[:3]
            row = {"samples": n, "serial_s": round(serial, 3),
                   "clamped_pixel_fraction": round(float(clamped.sum() / n_pts.sum()), 6),
                   "most_clamped_types": {plan.types[int(i)].name: round(
                       float(clamped[i] / max(n_pts[i], 1)), 4) for i in worst},
                   "clipped_samples": int(sum(int(s.clipped.sum()) for s in shards)),
                   "samples_per_s_1proc": round(n / serial, 1),
                   "rays_per_s_1proc": round(rays / serial) if rays else None,
                   "points_per_sample": round(points / n, 1),
                   "bytes_per_sample": round(size / n, 1)}
            if backend != "blender-bvh" and args.workers > 1:
                for t in tasks:
                    os.remove(t.path)
                # Blender: one process per shard in the real build. Here shards are smaller
                # (per-type subsets), so the process start is charged per real shard below.
                pool_s = run_pool(tasks, args.workers, None)
                row["pool_s"] = round(pool_s, 3)
                row[f"samples_per_s_{args.workers}proc"] = round(n / pool_s, 1)
                per_sample = pool_s / n
            else:
                per_sample = serial / n / args.workers
            extra = 0.0
            if backend.startswith("blender"):
                # measured start of a fresh bpy process + catalog, paid once per real shard
                t0 = time.perf_counter()
                import subprocess
                subprocess.run([sys.executable, "-c", "import bpy; "
                                "bpy.ops.wm.read_factory_settings(use_empty=True); "
                                "import dataset_builder.build"], check=True,
                               cwd=Path(__file__).resolve().parents[1])
                start_s = time.perf_counter() - t0
                row["process_start_s"] = round(start_s, 3)
                extra = start_s * len(plan.shards) / args.workers
            row["full_build_min"] = round((per_sample * n_full + extra) / 60, 2)
            row["full_size_GB"] = round(size / n * n_full / 1e9, 2)
            results["backends"][backend] = row
            print(backend, json.dumps(row), flush=True)
        ref = tmp / "embree"
        emb_tasks = subset_tasks(plan, catalog, args.per_type, ref, "embree")
        rate, n_rays = raw_embree_rate(plan, catalog, emb_tasks)
        results["raw_embree_rays_per_s"] = round(rate)
        results["raw_embree_rays"] = n_rays
        if "embree" in results["backends"]:
            # the pipeline's figure includes one BVH build and one shard write per type, which
            # these per-type subsets (not real 2500-sample shards) pay often: see
            # bench/build_floor.py for the ratio on real shards
            pipe = results["backends"]["embree"]["rays_per_s_1proc"]
            results["raw_over_pipeline_embree"] = round(rate / pipe, 3)
        for t in emb_tasks:
            run_task(t)
        for backend in results["backends"]:
            if backend in ("embree", "blender-bvh"):
                continue
            results["backends"][backend]["vs_embree"] = agreement(
                ref, tmp / backend, backend, len(plan.types))
    emit(results, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
