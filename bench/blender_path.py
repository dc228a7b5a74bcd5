"""The Blender backend's build against the embree build, on the same real shards, in one run
(issue 22, point 2).

    .venv/bin/python bench/blender_path.py [--types 4] [--samples 2500] [--repeat 1]
                                           [--blender-binary] [--json out.json]

Shards as bench/build_floor.py picks them: the first training shard of ``--types`` types spread
over the paper-table1 type list, ``--samples`` rows each (2500 is a real shard). Each path runs
the builder's own shard pipeline in one process, I/O included (conditions -> rays -> ray casting
-> cells -> shard bytes -> file written, fsynced, renamed; each type's caster built once, as a
build does): embree, then ``--backend blender`` through the ``bpy`` module in this process, and
with ``--blender-binary`` the same inside ``blender -b -P`` (this file, run by the binary on
PATH; its start and warm-up are reported apart, not in the build time). Rounds alternate the
paths so that a machine whose speed drifts moves them together; the ratios (Blender's time over
embree's) of the best round are the figures to quote, every round's are listed too. CPU
seconds (all threads of the process) are given beside wall seconds: Blender's Geometry Nodes
evaluation runs on every core, embree's path on one, so on a busy machine the wall ratio
moves with the load and the CPU ratio much less.

Beside the pipelines it times each caster's call alone on the pipeline's own float32 rays, in
the pipeline's blocks (``raw_*``: embree's ``distances32``; Blender's Geometry Nodes evaluation
with its I/O): ``raw_blender_cpu_over_raw_embree_cpu`` is the floor of the Blender path's ratio,
``bpy_cpu_over_raw_blender_cpu`` what the pipeline adds on top of Blender's own ray casting.
``oracle_blender_*``: Blender casting only the rays that embree finds a surface on, over the
whole embree pipeline: the best that any pre-filter of Blender's rays could reach.

It also checks the Blender shards against embree's cell for cell: the (sample, pixel) sets and
the stored ranges.

``measure(...)`` returns the same dict for a combined bench.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def shard_tasks(n_types: int, samples: int, out: Path, backend: str):
    """The first training shard of ``n_types`` types spread over the paper-table1 list (as
    bench/build_floor.py picks them), ``samples`` rows each, written under ``out``."""
    from apcg_core.catalog.catalog import default_catalog
    from dataset_builder.build import _task
    from dataset_builder.plan import ShardPlan, load_config, make_plan
    catalog = default_catalog()
    plan = make_plan(load_config("paper-table1"), catalog)
    codes = np.linspace(0, len(plan.types) - 1, n_types).round().astype(int)
    out.mkdir(parents=True, exist_ok=True)
    tasks = []
    for code in codes:
        first = next(s for s in plan.shards if s.type_code == code and s.split == "train")
        sp = ShardPlan(first.index, "train", int(code), first.rows[:samples])
        t = _task(plan, catalog, sp, out)
        t.backend = backend
        t.path = str(out / f"{backend}-{int(code):03d}.npz")
        tasks.append(t)
        catalog.mesh(t.type_catalog_index)  # meshes loaded before any timing
    return tasks


def pipeline_seconds(tasks) -> tuple[float, float]:
    """One build of ``tasks`` in this process (casters made and freed as a build does): wall
    seconds and this process's CPU seconds (every thread's)."""
    from dataset_builder.build import close_simulators, run_task
    t0, c0 = time.perf_counter(), time.process_time()
    for t in tasks:
        run_task(t)
    close_simulators()
    return time.perf_counter() - t0, time.process_time() - c0


def _warm(tasks) -> None:
    """Imports, compiled kernels' cache, Blender's first scene: paid before timing."""
    from dataset_builder.build import close_simulators, run_task
    run_task(tasks[0])
    close_simulators()


def raw_seconds(tasks, backend: str, block: int = 32_768,
                hits_only: bool = False) -> tuple[float, float]:
    """The ray caster's call alone on the pipeline's own float32 rays (made beforehand,
    untimed), in blocks of ``block`` rays as the pipeline calls it: wall and CPU seconds.
    embree: ``EmbreeCaster.distances32``; blender: Blender's Geometry Nodes evaluation with
    its I/O (``BlenderCaster._distances``: rays in, distances out).

    ``hits_only``: cast only the rays that embree finds a surface on (chosen untimed), as an
    oracle pre-filter would: no real filter of the rays can leave the caster less to do, so
    this is the floor of what filtering could buy (issue 22, point 2)."""
    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.lidar import LidarParams
    from dataset_builder.backends import make_caster
    from dataset_builder.rays import angular_boxes, bounding_radius, make_rays, sample_frames
    catalog = default_catalog()
    wall = cpu = 0.0
    for t in tasks:
        mesh = catalog.mesh(t.type_catalog_index)
        lidar = LidarParams.from_dict(t.lidar)
        radius = bounding_radius(mesh.vertices)
        m, c = sample_frames(t.table)
        boxes = angular_boxes(mesh.vertices, t.table, lidar, m, c)
        rays = make_rays(t.table, boxes, lidar, m, c, radius)
        o = np.ascontiguousarray(rays.origin, np.float32)
        d = np.ascontiguousarray(rays.direction, np.float32)
        limit = np.float32(rays.t_max)
        del rays
        if hits_only:
            hit = make_caster("embree", mesh).distances32(o, d, limit) < limit
            o, d = np.ascontiguousarray(o[hit]), np.ascontiguousarray(d[hit])
        caster = make_caster(backend, mesh)
        call = caster._distances if backend == "blender" else caster.distances32
        t0, c0 = time.perf_counter(), time.process_time()
        for i in range(0, len(o), block):
            call(o[i:i + block], d[i:i + block], limit)
        wall += time.perf_counter() - t0
        cpu += time.process_time() - c0
        if hasattr(caster, "close"):
            caster.close()
    return wall, cpu


def n_rays(tasks) -> int:
    from apcg_core.io.dataset import Shard
    return int(sum(Shard.load(t.path).n_rays.astype(np.int64).sum() for t in tasks))


def compare(ref_tasks, other_tasks) -> dict:
    """Cell for cell: the (sample, pixel) cells each shard holds, and for the common ones the
    stored range (float32 offset from r0, quantized to the 0.15 m bin's centre)."""
    from apcg_core.io.dataset import Shard
    only_ref = only_other = common = same_range = 0
    worst = 0.0
    for a_t, b_t in zip(ref_tasks, other_tasks, strict=True):
        a, b = Shard.load(a_t.path), Shard.load(b_t.path)
        assert np.array_equal(a.sample_id, b.sample_id)
        keys = []
        for s in (a, b):
            sample = np.repeat(np.arange(len(s)), np.diff(s.offsets))
            keys.append(sample * (1 << 20) + s.pixel.astype(np.int64))
        ka, kb = keys
        _, ia, ib = np.intersect1d(ka, kb, assume_unique=True, return_indices=True)
        common += len(ia)
        only_ref += len(ka) - len(ia)
        only_other += len(kb) - len(ib)
        ra, rb = a.delta_range_m[ia], b.delta_range_m[ib]
        same_range += int((ra == rb).sum())
        if len(ia):
            worst = max(worst, float(np.abs(ra.astype(np.float64) - rb).max()))
    return {"cells_common": common, "cells_only_embree": only_ref,
            "cells_only_blender": only_other,
            "cells_identical": only_ref == 0 and only_other == 0,
            "ranges_equal": same_range, "ranges_differing": common - same_range,
            "max_range_diff_m": worst}


def _binary_round(args_list: list[str]) -> dict:
    """One timed build inside ``blender -b -P`` (this file with --inside-blender)."""
    cmd = ["blender", "-b", "--factory-startup", "--python-exit-code", "1", "-P",
           str(Path(__file__).resolve()), "--", "--inside-blender", *args_list]
    t0 = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
    wall = time.perf_counter() - t0
    if run.returncode != 0:
        raise RuntimeError(f"blender -b failed ({run.returncode}):\n{run.stdout[-3000:]}\n"
                           f"{run.stderr[-3000:]}")
    line = next(x for x in run.stdout.splitlines()[::-1] if x.startswith("APCG-BENCH "))
    res = json.loads(line[len("APCG-BENCH "):])
    res["process_wall_s"] = round(wall, 3)
    return res


def _inside_blender(argv: list[str]) -> int:
    """Run by ``blender -b -P``: warm up, then time one build of the shards, print JSON."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--inside-blender", action="store_true")
    ap.add_argument("--types", type=int)
    ap.add_argument("--samples", type=int)
    ap.add_argument("--out")
    a = ap.parse_args(argv)
    import bpy
    t0 = time.perf_counter()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    tasks = shard_tasks(a.types, a.samples, Path(a.out), "blender")
    _warm(tasks)
    setup = time.perf_counter() - t0
    seconds, cpu = pipeline_seconds(tasks)
    res = {"blender_version": bpy.app.version_string, "seconds": seconds, "cpu_s": cpu,
           "setup_s": round(setup, 3)}
    print("APCG-BENCH " + json.dumps(res), flush=True)
    return 0


def measure(types: int = 4, samples: int = 2500, repeat: int = 1, binary: bool = False,
            check: bool = True, raw: bool = True) -> dict:
    """Time embree's and the Blender backend's builds of the same shards, ``repeat`` rounds
    alternating the paths; ratios are Blender's seconds over embree's in the same round."""
    import bpy

    from dataset_builder import kernels
    bpy.ops.wm.read_factory_settings(use_empty=True)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        emb = shard_tasks(types, samples, tmp / "embree", "embree")
        bl = shard_tasks(types, samples, tmp / "bpy", "blender")
        _warm(emb)
        _warm(bl)
        rounds = []
        for _ in range(repeat):
            r = {}
            r["embree_s"], r["embree_cpu_s"] = pipeline_seconds(emb)
            r["bpy_s"], r["bpy_cpu_s"] = pipeline_seconds(bl)
            if binary:
                b = _binary_round(["--types", str(types), "--samples", str(samples), "--out",
                                   str(tmp / "binary")])
                r["binary_s"] = b["seconds"]
                r["binary_cpu_s"] = b["cpu_s"]
                r["binary_setup_s"] = b["setup_s"]
                r["binary_process_wall_s"] = b["process_wall_s"]
                r["binary_version"] = b["blender_version"]
            if raw:
                r["raw_embree_s"], r["raw_embree_cpu_s"] = raw_seconds(emb, "embree")
                r["raw_blender_s"], r["raw_blender_cpu_s"] = raw_seconds(bl, "blender")
                r["raw_blender_over_raw_embree"] = r["raw_blender_s"] / r["raw_embree_s"]
                r["raw_blender_cpu_over_raw_embree_cpu"] = (r["raw_blender_cpu_s"]
                                                           / r["raw_embree_cpu_s"])
                r["bpy_cpu_over_raw_blender_cpu"] = r["bpy_cpu_s"] / r["raw_blender_cpu_s"]
                r["oracle_blender_s"], r["oracle_blender_cpu_s"] = raw_seconds(
                    bl, "blender", hits_only=True)
                r["oracle_blender_over_embree"] = r["oracle_blender_s"] / r["embree_s"]
                r["oracle_blender_cpu_over_embree_cpu"] = (r["oracle_blender_cpu_s"]
                                                          / r["embree_cpu_s"])
            r["bpy_over_embree"] = r["bpy_s"] / r["embree_s"]
            r["bpy_cpu_over_embree_cpu"] = r["bpy_cpu_s"] / r["embree_cpu_s"]
            if binary:
                r["binary_over_embree"] = r["binary_s"] / r["embree_s"]
                r["binary_cpu_over_embree_cpu"] = r["binary_cpu_s"] / r["embree_cpu_s"]
            rounds.append(r)
        rays = n_rays(emb)
        assert n_rays(bl) == rays
        best = min(rounds, key=lambda r: r["bpy_over_embree"])
        res = {"command": "python bench/blender_path.py " + shlex.join(sys.argv[1:]),
               "machine": {"cpus": os.cpu_count(), "bpy": bpy.app.version_string,
                           "compiled_kernels": kernels.enabled()},
               "shards": len(emb), "samples": sum(len(t.rows) for t in emb), "rays": rays,
               "embree_rays_per_s": round(rays / best["embree_s"]),
               "bpy_rays_per_s": round(rays / best["bpy_s"]),
               "bpy_over_embree": round(best["bpy_over_embree"], 3),
               "bpy_cpu_over_embree_cpu": round(best["bpy_cpu_over_embree_cpu"], 3)}
        if raw:
            res["raw_blender_cpu_over_raw_embree_cpu"] = round(
                best["raw_blender_cpu_over_raw_embree_cpu"], 3)
            res["bpy_cpu_over_raw_blender_cpu"] = round(best["bpy_cpu_over_raw_blender_cpu"], 3)
            # Blender casting only the rays that hit, nothing else timed, over the whole
            # embree pipeline: what a perfect pre-filter of the rays would leave
            res["oracle_blender_over_embree"] = round(
                min(r["oracle_blender_over_embree"] for r in rounds), 3)
            res["oracle_blender_cpu_over_embree_cpu"] = round(
                min(r["oracle_blender_cpu_over_embree_cpu"] for r in rounds), 3)
        if binary:
            bb = min(rounds, key=lambda r: r["binary_over_embree"])
            res.update({"blender_binary": bb["binary_version"],
                        "binary_rays_per_s": round(rays / bb["binary_s"]),
                        "binary_over_embree": round(bb["binary_over_embree"], 3),
                        "binary_cpu_over_embree_cpu": round(bb["binary_cpu_over_embree_cpu"], 3),
                        "binary_start_and_warmup_s": bb["binary_setup_s"]})
        res["rounds"] = [{k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()}
                         for r in rounds]
        if check:
            res["bpy_vs_embree"] = compare(emb, bl)
            if binary:
                bin_tasks = shard_tasks(types, samples, tmp / "binary", "blender")
                res["binary_vs_embree"] = compare(emb, bin_tasks)
    return res


def main() -> int:
    from bench_output import emit

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--types", type=int, default=4, help="types (one real shard each)")
    ap.add_argument("--samples", type=int, default=2500, help="samples per shard")
    ap.add_argument("--repeat", type=int, default=1, help="timed rounds (best ratio kept)")
    ap.add_argument("--blender-binary", action="store_true",
                    help="also time the build inside `blender -b -P` (the binary on PATH)")
    ap.add_argument("--no-check", action="store_true", help="skip the cell-for-cell check")
    ap.add_argument("--no-raw", action="store_true",
                    help="skip timing the casters' calls alone on the same rays")
    ap.add_argument("--json", help="write the results here too")
    args = ap.parse_args()
    res = measure(args.types, args.samples, args.repeat, args.blender_binary,
                  not args.no_check, not args.no_raw)
    emit(res, args.json)
    return 0


if __name__ == "__main__":
    if "--inside-blender" in sys.argv:
        _argv = sys.argv[sys.argv.index("--") + 1:]
        sys.stdout.flush()
        _code = _inside_blender(_argv)
        if _code:
            sys.exit(_code)
    else:
        sys.exit(main())
