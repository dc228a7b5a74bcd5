"""The build's scale figures in one run (issue 22, point 5): rays/s of raw embree, the embree
pipeline, the Blender path (bpy) and a 2-worker engine build, with their ratios, and the cost
per sample of whole builds from 10^3 to 10^6 samples (flat is the goal).

    .venv/bin/python bench/scale.py [--max-samples 1000000] [--workers 2] \
        [--json bench/results/scale.json]

Each part is its own bench's function, so the figures mean what those benches say:
``bench/build_floor.py`` (embree on the first training shard of 8 types, the best round's
ratio), ``bench/blender_path.py`` (the same pipeline through ``--backend blender`` on 4 shards),
``dataset_builder.build.time_engine_build`` (a whole build of the cpu-like config below, cluster
start-up included, against the local pool on the same config; the local pool again with the
Blender backend). The Blender path's ``oracle`` figures are Blender casting only the rays that
hit, against the whole embree pipeline: the floor under any pre-filter of its rays. The sizes
are builds of one config (random sampling over every built-in type), complete, from a fresh
directory, the local pool with ``--workers`` processes.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "bench"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))


def sized_config(samples: int) -> dict:
    """Random Table 1 conditions over every built-in type, about ``samples`` in all."""
    from apcg_core.catalog.catalog import default_catalog
    n_types = sum(t.source == "builtin" for t in default_catalog())
    return {"name": f"scale-{samples}", "seed": 11, "sampling": "random", "types": "all",
            "samples_per_type": max(1, round(samples / n_types)), "shard_size": 2500}


def main() -> int:
    from bench_output import emit

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--max-samples", type=int, default=10**6)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", help="also write the result here")
    a = ap.parse_args()

    import blender_path
    import build_floor

    from dataset_builder.build import time_engine_build
    t_start = time.perf_counter()
    floor = build_floor.measure(n_types=8, samples=2500, repeat=2)
    blender = blender_path.measure(types=4, samples=2500, repeat=1, check=False, raw=True)
    engine_cfg = sized_config(50_000)
    dask = time_engine_build(engine_cfg, engine="dask", workers=a.workers)
    pool = time_engine_build(engine_cfg, engine="local", workers=a.workers)
    # the same whole build with the Blender backend: what a user of --backend blender waits
    blender_build = time_engine_build({**engine_cfg, "backend": "blender"}, engine="local",
                                      workers=a.workers)
    sizes = []
    n = 1000
    while n <= a.max_samples:
        r = time_engine_build(sized_config(n), engine="local", workers=a.workers)
        sizes.append({"samples": r["samples"], "seconds": r["seconds"],
                      "us_per_sample": round(1e6 * r["seconds"] / r["samples"], 1),
                      "rays_per_s": round(r["rays"] / r["seconds"])})
        print(json.dumps(sizes[-1]), file=sys.stderr, flush=True)
        n *= 10
    raw, pipe = floor["raw_embree_rays_per_s"], floor["pipeline_rays_per_s"]
    res = {
        "command": "python bench/scale.py " + shlex.join(sys.argv[1:]),
        "cpus": os.cpu_count(), "load_at_start": os.getloadavg()[0],
        "rays_per_s": {"raw_embree": raw, "embree_pipeline": pipe,
                       "blender_bpy": blender["bpy_rays_per_s"],
                       "engine_dask_2_workers": round(dask["rays"] / dask["seconds"]),
                       "local_pool_2_workers": round(pool["rays"] / pool["seconds"])},
        "ratios": {"embree_pipeline_over_raw": floor["pipeline_over_raw"],
                   "blender_bpy_over_embree_pipeline": blender["bpy_over_embree"],
                   "blender_bpy_cpu_over_embree_cpu": blender["bpy_cpu_over_embree_cpu"],
                   "blender_oracle_over_embree_pipeline": blender["oracle_blender_over_embree"],
                   "blender_oracle_cpu_over_embree_cpu":
                       blender["oracle_blender_cpu_over_embree_cpu"],
                   "blender_build_over_embree_build_seconds":
                       round(blender_build["seconds"] / pool["seconds"], 3),
                   "dask_over_local_pool_seconds": round(dask["seconds"] / pool["seconds"], 3)},
        "engine_build": {"dask": dask, "local_pool": pool, "local_pool_blender": blender_build},
        "cost_per_sample": sizes,
        "cost_per_sample_last_over_first": round(sizes[-1]["us_per_sample"]
                                                 / sizes[0]["us_per_sample"], 3),
        "seconds": round(time.perf_counter() - t_start, 1)}
    emit(res, a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
