"""Peak memory of a long Blender-backend build, shard by shard (issue 20).

    .venv/bin/python bench/build_memory.py [--samples 100000] [--shard-size 2500]
        [--types A320neo,...] [--mode both|in-process|per-process] [--json out.json]
        [--backend blender|embree] [--sensor PRESET]

Builds a dataset with ``backend = "blender"`` (the ``bpy`` module; ``--backend embree`` for
embree, ``--sensor`` for a photon build, issue "Photons") from a config written to a
temporary directory: ``--samples`` conditions drawn at random over a few types, shards of
``--shard-size`` samples (10^5 / 2500: 40 shards), one worker, and records the peak resident
memory of every shard:

* ``in-process``: ``apcg dataset build --workers 1`` (the default): every shard in the build's
  own process, one after the other. The process's peak (VmHWM) is reset before each shard
  (``/proc/self/clear_refs``), so each shard's figure is its own peak; VmRSS after the shard
  and Blender's data-block counts show whether anything is left behind.
* ``per-process``: ``--workers 1 --tasks-per-process 1`` (what ``--workers N`` does for the
  Blender backends): a fresh process per shard; each one's peak over its whole life (bpy start
  included) and the parent's peak.

The figures to quote: first shard, last shard, the largest, and the slope of a straight line
through them (MB per shard). Linux only (reads /proc/self/status).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from dataset_builder import build  # noqa: E402

_RUN_TASK = build.run_task  # the real one (a spawned worker imports this file unpatched)
LOG_ENV = "APCG_MEMORY_LOG"
RESET_ENV = "APCG_MEMORY_RESET"


def _status_kb() -> dict:
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmHWM", "VmRSS"):
                out[key] = int(value.split()[0])
    return out


def _blender_blocks() -> int | None:
    if "bpy" not in sys.modules:
        return None
    import bpy
    d = bpy.data
    return (len(d.scenes) + len(d.objects) + len(d.meshes) + len(d.node_groups)
            + len(d.collections))


def measured_run_task(task):
    """build.run_task, logging this process's memory around it (one JSON line per shard)."""
    from bench_output import append_line
    if os.environ.get(RESET_ENV) == "1":
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # VmHWM := VmRSS: the peak below is this shard's own
    before = _status_kb()
    t0 = time.perf_counter()
    result = _RUN_TASK(task)
    seconds = time.perf_counter() - t0
    after = _status_kb()
    row = {"shard": task.index, "pid": os.getpid(), "samples": len(task.rows),
           "seconds": round(seconds, 3), "rss_before_mb": round(before["VmRSS"] / 1024, 1),
           "peak_mb": round(after["VmHWM"] / 1024, 1),
           "rss_after_mb": round(after["VmRSS"] / 1024, 1),
           "blender_blocks_after": _blender_blocks()}
    append_line(os.environ[LOG_ENV], json.dumps(row))  # the run's own temporary directory
    return result


def config_text(samples: int, shard_size: int, types: list[str], backend: str = "blender",
                sensor: str | None = None) -> str:
    per_type = -(-samples // len(types))
    names = ", ".join(json.dumps(t) for t in types)
    return (f'description = "memory bench: {len(types)} types x {per_type} random conditions"\n'
            f'seed = 11\nbackend = "{backend}"\nshard_size = {shard_size}\n'
            f'test_fraction = 0.2\nquantize = true\n'
            f'supersample = {4 if sensor else 1}\nsampling = "random"\n'
            f'samples_per_type = {per_type}\ntypes = [{names}]\n'
            + (f'sensor = "{sensor}"\n' if sensor else ""))


def run_mode(mode: str, cfg_path: Path, out: Path, log: Path) -> dict:
    os.environ[LOG_ENV] = str(log)
    os.environ[RESET_ENV] = "1" if mode == "in-process" else "0"
    build.run_task = measured_run_task  # build_dataset's loop calls build.run_task
    t0 = time.perf_counter()
    try:
        summary = build.build_dataset(str(cfg_path), out, workers=1, progress=False,
                                      tasks_per_process=1 if mode == "per-process" else None)
    finally:
        build.run_task = _RUN_TASK
    wall = time.perf_counter() - t0
    rows = [json.loads(x) for x in log.read_text().splitlines()]
    # in the order the shards were built (the log's order)
    peaks = np.array([r["peak_mb"] for r in rows])
    idx = np.arange(len(rows))
    slope = float(np.polyfit(idx, peaks, 1)[0]) if len(rows) > 1 else 0.0
    res = {"mode": mode, "shards": len(rows), "samples": int(sum(r["samples"] for r in rows)),
           "wall_s": round(wall, 1), "build_summary_s": summary["seconds"],
           "processes": len({r["pid"] for r in rows}),
           "peak_first_mb": rows[0]["peak_mb"], "peak_last_mb": rows[-1]["peak_mb"],
           "peak_max_mb": float(peaks.max()), "peak_min_mb": float(peaks.min()),
           "peak_slope_mb_per_shard": round(slope, 3),
           "parent_peak_mb": round(_status_kb()["VmHWM"] / 1024, 1),
           "per_shard": rows}
    if mode == "in-process":
        res["rss_after_first_mb"] = rows[0]["rss_after_mb"]
        res["rss_after_last_mb"] = rows[-1]["rss_after_mb"]
        # the parent is the process that built every shard: its peak is the largest shard's
        res.pop("parent_peak_mb")
    return res


def table(res: dict) -> str:
    lines = [f"mode {res['mode']}: {res['shards']} shards, {res['samples']} samples, "
             f"{res['processes']} process(es), {res['wall_s']} s",
             "| shard | samples | s | peak MB | RSS after MB | Blender blocks |",
             "|---|---|---|---|---|---|"]
    for r in res["per_shard"]:
        lines.append(f"| {r['shard']} | {r['samples']} | {r['seconds']} | {r['peak_mb']} | "
                     f"{r['rss_after_mb']} | {r['blender_blocks_after']} |")
    lines.append(f"peak: first {res['peak_first_mb']} MB, last {res['peak_last_mb']} MB, "
                 f"max {res['peak_max_mb']} MB, slope {res['peak_slope_mb_per_shard']} MB/shard"
                 + (f"; parent peak {res['parent_peak_mb']} MB" if "parent_peak_mb" in res
                    else ""))
    return "\n".join(lines)


def _child(mode: str, cfg: Path, work: Path, out_json: Path) -> None:
    """One mode, in a process of its own (so that one mode's memory never shows in the
    other's, and the parent of a per-process build has not imported bpy itself)."""
    from bench_output import write_text
    if mode == "in-process" and 'backend = "blender"' in cfg.read_text():
        import bpy
        bpy.ops.wm.read_factory_settings(use_empty=True)
    res = run_mode(mode, cfg, work / mode, work / f"{mode}.jsonl")
    write_text(out_json, json.dumps(res))  # into the parent's temporary directory


def main() -> int:
    from bench_output import emit, write_text

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--shard-size", type=int, default=2500)
    ap.add_argument("--types", default="A320neo,777-300ER,F-16C Fighting Falcon,Mavic 3")
    ap.add_argument("--mode", default="both", choices=["both", "in-process", "per-process"])
    ap.add_argument("--json", help="write the results here too")
    ap.add_argument("--backend", default="blender", choices=["blender", "embree"])
    ap.add_argument("--sensor", help="a sensor preset: a photon build (issue Photons)")
    ap.add_argument("--child", nargs=3, metavar=("CONFIG", "WORKDIR", "RESULT"),
                    help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        _child(args.mode, *(Path(x) for x in args.child))
        return 0
    import subprocess

    types = [t.strip() for t in args.types.split(",")]
    modes = ["in-process", "per-process"] if args.mode == "both" else [args.mode]
    version = None
    if args.backend == "blender":
        import bpy
        version = bpy.app.version_string
    results = {"command": "python bench/build_memory.py " + shlex.join(sys.argv[1:]),
               "machine": {"cpus": os.cpu_count(), "bpy": version},
               "types": types, "modes": {}}
    # the config, the children's results and logs: a fresh temporary directory of this run's
    # own (no refusal); --json, the one file asked for, is replaced in place (bench_output)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cfg = tmp / "memory.toml"
        write_text(cfg, config_text(args.samples, args.shard_size, types, args.backend,
                                    args.sensor))
        results["config"] = cfg.read_text()
        for mode in modes:
            out = tmp / f"{mode}.json"
            subprocess.run([sys.executable, __file__, "--mode", mode, "--child", str(cfg),
                            str(tmp), str(out)], check=True)
            res = json.loads(out.read_text())
            results["modes"][mode] = res
            print(table(res), flush=True)
    summary = {m: {k: v for k, v in r.items() if k != "per_shard"}
               for m, r in results["modes"].items()}
    emit(summary)
    emit(results, args.json, show=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
