"""How close the embree build comes to embree itself, in one run (issue 22).

    .venv/bin/python bench/build_floor.py [--types 8] [--samples 2500] [--repeat 2] [--stages]
                                          [--profile]

On real shards of the paper-table1 plan (the first training shard of ``--types`` types spread
over the type list, ``--samples`` rows each: 2500 is a real shard) it times the builder's own
shard pipeline, one process, I/O included (conditions -> rays -> embree -> cells -> shard bytes
-> file written, fsynced, renamed; each type's BVH built once, as a build does), and embree's
call alone on exactly the same float32 rays. It prints both rates and their ratio, the figure
to quote: both are measured in the same run, so a busy machine moves them together (the same
ratio in CPU seconds is printed beside it: on a shared machine it moves less).
``--stages`` also prints each stage's wall and CPU seconds in one more round, ``--profile`` a
pyinstrument profile of one more round (which sees nothing inside the compiled kernels).
``APCG_KERNELS=numpy`` in the environment times the numpy path instead of the compiled kernels.
:func:`rates` returns the two rates for a combined bench.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(1, str(Path(__file__).resolve().parent))  # bench/simulate.py, when imported

from apcg_core.catalog.catalog import default_catalog  # noqa: E402
from apcg_core.io.dataset import Shard  # noqa: E402
from dataset_builder import kernels  # noqa: E402
from dataset_builder.build import _task, close_simulators, run_task  # noqa: E402
from dataset_builder.plan import ShardPlan, load_config, make_plan  # noqa: E402

BLOCK = 32_768


def shard_tasks(plan, catalog, n_types: int, samples: int, out: Path):
    codes = np.linspace(0, len(plan.types) - 1, n_types).round().astype(int)
    tasks = []
    for code in codes:
        first = next(s for s in plan.shards if s.type_code == code and s.split == "train")
        sp = ShardPlan(first.index, "train", int(code), first.rows[:samples])
        tasks.append(_task(plan, catalog, sp, out))
    return tasks


def pipeline_seconds(tasks) -> float:
    return pipeline_times(tasks)[0]


def pipeline_times(tasks) -> tuple[float, float]:
    """Wall and CPU seconds of the builder's pipeline on these shard tasks."""
    c0, t0 = time.process_time(), time.perf_counter()
    for t in tasks:
        run_task(t)
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    close_simulators()
    return elapsed, cpu


def stage_times(tasks) -> dict:
    """Wall and CPU seconds of each stage of one pipeline round, from timers put around the
    functions that do them (a profiler cannot see inside the compiled kernels)."""
    import apcg_core.io.dataset as dataset_io
    import dataset_builder.rays as rays
    import dataset_builder.shards as shards
    import dataset_builder.simulate as simulate
    from apcg_core.lidar import LidarParams
    from dataset_builder.backends.embree import EmbreeCaster

    acc: dict = {}

    def timed(key, f):
        def g(*a, **k):
            c0, t0 = time.process_time(), time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                w, c = acc.get(key, (0.0, 0.0))
                acc[key] = (w + time.perf_counter() - t0, c + time.process_time() - c0)
        return g

    swaps = [(simulate, "angular_boxes"), (simulate, "cast_cells"), (rays, "_block"),
             (rays.RayBlock, "cells"), (EmbreeCaster, "distances32"), (EmbreeCaster, "cast_hits"),
             (LidarParams, "quantize_range"), (simulate, "refine_ranges"),
             (shards, "compute_shard"),
             (dataset_io.Shard, "to_bytes"), (shards, "write_atomic")]
    if kernels.loaded():
        k = kernels.require()
        swaps += [(k, "row_elevations"), (k, "rays"), (k, "hits"), (k, "screen")]
    saved = [(obj, name, getattr(obj, name)) for obj, name in swaps]
    for obj, name, f in saved:
        setattr(obj, name, timed(name, f))
    try:
        total = pipeline_times(tasks)
    finally:
        for obj, name, f in saved:
            setattr(obj, name, f)
    z = (0.0, 0.0)

    def sub(a, *b):
        return tuple(x - sum(y[i] for y in b) for i, x in enumerate(a))

    def add(*a):
        return tuple(sum(x[i] for x in a) for i in range(2))

    embree = acc.get("distances32", z)
    # numpy path: embree is called inside cast_hits; compiled path: cast_hits is not called
    in_cast_hits = sub(acc["cast_hits"], embree) if "cast_hits" in acc else z
    hits = add(in_cast_hits, acc.get("cells", z), acc.get("hits", z))
    raygen = add(acc.get("_block", z), acc.get("rays", z), acc.get("row_elevations", z))
    stages = {
        "embree's call": embree,
        "ray generation": raygen,
        "angular boxes": acc.get("angular_boxes", z),
        "hit post-processing": hits,
        "rest of cast_cells (per-table set-up, block loop)":
            sub(acc.get("cast_cells", z), embree, raygen, hits),
        "quantisation": acc.get("quantize_range", z),
        "float64 ranges at bin edges (refine_ranges)": acc.get("refine_ranges", z),
        "shard arrays (compute_shard's own numpy)":
            sub(acc.get("compute_shard", z), acc.get("angular_boxes", z), acc.get("cast_cells", z),
                acc.get("quantize_range", z), acc.get("refine_ranges", z)),
        "zip bytes": acc.get("to_bytes", z),
        "write, fsync, rename": acc.get("write_atomic", z),
    }
    stages["frames, BVH builds, rest"] = sub(total, *stages.values())
    stages["total"] = total
    return {k: [round(v[0], 3), round(v[1], 3)] for k, v in stages.items()}


def raw_embree_seconds(plan, catalog, tasks) -> tuple[float, int]:
    """embree's call alone on the pipeline's own float32 rays, in the pipeline's blocks."""
    wall, _, rays = raw_embree_times(plan, catalog, tasks)
    return wall, rays


def raw_embree_times(plan, catalog, tasks) -> tuple[float, float, int]:
    """:func:`raw_embree_seconds` as (wall seconds, CPU seconds, rays)."""
    from simulate import raw_embree_times as times_in_blocks  # bench/simulate.py
    return times_in_blocks(plan, catalog, tasks, block=BLOCK)


def measure(n_types: int = 8, samples: int = 2500, repeat: int = 2,
            profile: bool = False, stages: bool = False) -> dict:
    """Both rates on the first training shard of ``n_types`` types, timed in one run (the best
    round's ratio kept); with ``profile`` a pyinstrument profile of one more pipeline round,
    with ``stages`` the [wall, CPU] seconds of each stage of one more round."""
    catalog = default_catalog()
    plan = make_plan(load_config("paper-table1"), catalog)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        (out / "shards").mkdir()
        tasks = shard_tasks(plan, catalog, n_types, samples, out)
        for t in tasks:
            catalog.mesh(t.type_catalog_index)  # the catalog's meshes: loaded before timing
        if kernels.enabled():
            kernels.require()  # loaded, as a build has them after its first ~4 M rays
        run_task(tasks[0])  # warm: imports, compiled kernels' first calls, first caster
        close_simulators()
        rounds = []
        for _ in range(repeat):
            pipe, pipe_cpu = pipeline_times(tasks)
            raw, raw_cpu, n_rays = raw_embree_times(plan, catalog, tasks)
            rounds.append((pipe / raw, pipe, raw, pipe_cpu / raw_cpu))
        ratio, pipe, raw, _ = min(rounds)
        rays = int(sum(Shard.load(t.path).n_rays.astype(np.int64).sum() for t in tasks))
        assert rays == n_rays, (rays, n_rays)
        res = {"shards": len(tasks), "samples": sum(len(t.rows) for t in tasks), "rays": rays,
               "compiled_kernels": kernels.loaded(),
               "raw_embree_rays_per_s": round(rays / raw),
               "pipeline_rays_per_s": round(rays / pipe),
               "pipeline_over_raw": round(ratio, 3),
               "all_rounds_ratio": [round(r[0], 3) for r in rounds],
               # the same ratio in CPU seconds of this process: what a busy machine moves less
               # (the pipeline's fsync waits are not in it)
               "all_rounds_cpu_ratio": [round(r[3], 3) for r in rounds]}
        if stages:
            res["stages_wall_cpu_s"] = stage_times(tasks)
        if profile:
            from pyinstrument import Profiler
            prof = Profiler(interval=0.0005)
            prof.start()
            pipeline_seconds(tasks)
            prof.stop()
            res["profile"] = prof.output_text(unicode=False, color=False)
    return res


def rates(n_types: int = 8, samples: int = 2500, repeat: int = 2) -> tuple[float, float]:
    """(raw embree rays/s, pipeline rays/s), both from the round with the best ratio of one
    run: for a combined bench."""
    res = measure(n_types, samples, repeat)
    return float(res["raw_embree_rays_per_s"]), float(res["pipeline_rays_per_s"])


def main() -> int:
    from bench_output import emit

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--types", type=int, default=8, help="types (one real shard each)")
    ap.add_argument("--samples", type=int, default=2500, help="samples per shard")
    ap.add_argument("--repeat", type=int, default=2, help="timed rounds (best one kept)")
    ap.add_argument("--profile", action="store_true", help="print a pyinstrument profile")
    ap.add_argument("--stages", action="store_true",
                    help="print each stage's wall and CPU seconds (one more round)")
    ap.add_argument("--json", help="write the results here too")
    args = ap.parse_args()
    res = {"command": "python bench/build_floor.py " + shlex.join(sys.argv[1:]),
           **measure(args.types, args.samples, args.repeat, args.profile, args.stages)}
    profile = res.pop("profile", None)
    emit(res, args.json)
    if profile:
        print(profile)
    return 0


if __name__ == "__main__":
    sys.exit(main())
