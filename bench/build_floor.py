"""How close the embree build comes to embree itself, in one run (issue 22).

    .venv/bin/python bench/build_floor.py [--types 8] [--samples 2500] [--repeat 2] [--profile]

On real shards of the paper-table1 plan (the first training shard of ``--types`` types spread
over the type list, ``--samples`` rows each: 2500 is a real shard) it times the builder's own
shard pipeline, one process, I/O included (conditions -> rays -> embree -> cells -> shard bytes
-> file written, fsynced, renamed; each type's BVH built once, as a build does), and embree's
call alone on exactly the same float32 rays. It prints both rates and their ratio, the figure
to quote: both are measured in the same run, so a busy machine moves them together.
``--profile`` also prints where the pipeline's time goes (pyinstrument).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.catalog.catalog import default_catalog  # noqa: E402
from apcg_core.io.dataset import Shard  # noqa: E402
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
    t0 = time.perf_counter()
    for t in tasks:
        run_task(t)
    elapsed = time.perf_counter() - t0
    close_simulators()
    return elapsed


def raw_embree_seconds(plan, catalog, tasks) -> tuple[float, int]:
    """embree's call alone on the pipeline's own float32 rays, in the pipeline's blocks."""
    from simulate import raw_embree_seconds as seconds_in_blocks  # bench/simulate.py
    return seconds_in_blocks(plan, catalog, tasks, block=BLOCK)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--types", type=int, default=8, help="types (one real shard each)")
    ap.add_argument("--samples", type=int, default=2500, help="samples per shard")
    ap.add_argument("--repeat", type=int, default=2, help="timed rounds (best one kept)")
    ap.add_argument("--profile", action="store_true", help="print a pyinstrument profile")
    ap.add_argument("--json", help="write the results here too")
    args = ap.parse_args()

    catalog = default_catalog()
    plan = make_plan(load_config("paper-table1"), catalog)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        (out / "shards").mkdir()
        tasks = shard_tasks(plan, catalog, args.types, args.samples, out)
        for t in tasks:
            catalog.mesh(t.type_catalog_index)  # the catalog's meshes: loaded before timing
        run_task(tasks[0])  # warm: imports, first caster
        close_simulators()
        rounds = []
        for _ in range(args.repeat):
            pipe = pipeline_seconds(tasks)
            raw, n_rays = raw_embree_seconds(plan, catalog, tasks)
            rounds.append((pipe / raw, pipe, raw))
        ratio, pipe, raw = min(rounds)
        rays = int(sum(Shard.load(t.path).n_rays.astype(np.int64).sum() for t in tasks))
        assert rays == n_rays, (rays, n_rays)
        res = {"command": "python bench/build_floor.py " + " ".join(sys.argv[1:]),
               "shards": len(tasks), "samples": sum(len(t.rows) for t in tasks), "rays": rays,
               "raw_embree_rays_per_s": round(rays / raw),
               "pipeline_rays_per_s": round(rays / pipe),
               "pipeline_over_raw": round(ratio, 3),
               "all_rounds_ratio": [round(r[0], 3) for r in rounds]}
        print(json.dumps(res, indent=1))
        if args.json:
            Path(args.json).write_text(json.dumps(res, indent=1) + "\n")
        if args.profile:
            from pyinstrument import Profiler
            prof = Profiler(interval=0.0005)
            prof.start()
            pipeline_seconds(tasks)
            prof.stop()
            print(prof.output_text(unicode=False, color=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
