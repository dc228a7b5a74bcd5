"""Generation against exact simulation, whole commands, on the same conditions, in one run.

    .venv/bin/python bench/generate_vs_build.py --model DIR [--per-type 168] [--repeats 3]
        [--workers 2] [--json bench/results/generate_vs_build.json]
    .venv/bin/python bench/generate_vs_build.py --model DIR --workloads issue34 --repeats 1

``--workloads issue34`` runs the four workloads of the issue "The generator earns its place"
instead of the one below, each a dataset config of its own: 2 types on a Table-1 style grid
(16,384 and 102,400 clouds), 10 types at random conditions (100,000) and all 98 types on a
168-condition grid (16,464); each figure with the peak RSS of each command.

1. A random Table-1 dataset config over every built-in type (``--per-type`` conditions each:
   168 x 98 = 16,464 clouds by default) is written and built once, to fix the conditions.
2. Timed, alternating, ``--repeats`` times each (medians reported, with their ratio):
   ``apcg dataset build --config that.toml -o D --workers W`` (embree, the exact standard clouds,
   shards written) and ``apcg generate --model DIR --conditions D/conditions.csv -o clouds.npz``
   (the same conditions: conditions in, one file out).
The ratio generate / build is the issue's figure of merit (<= 1.0: generation is no slower).
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
APCG = [sys.executable, "-m", "apcg_core.cli"]

HEAD = """description = "bench: {what}"
seed = 11
backend = "embree"
shard_size = {shard}
test_fraction = 0.2
quantize = true
supersample = 1
types = {types}
"""


def random_config(what: str, types: str, n: int, shard: int = 2500) -> str:
    return (HEAD.format(what=what, shard=shard, types=types)
            + f'sampling = "random"\nsamples_per_type = {n}\n')


def grid_config(what: str, types: str, **counts) -> str:
    return (HEAD.format(what=what, shard=2500, types=types) + 'sampling = "grid"\n\n[counts]\n'
            + "".join(f"{k} = {v}\n" for k, v in counts.items()))


TYPES_2 = '["A320neo", "737-800"]'
TYPES_10 = ('["A320neo", "737-800", "G650ER", "G550", "777-300ER", "F-16C Fighting Falcon", '
            '"UH-60 Black Hawk", "Matrice 300 RTK", "Mavic 3", "eBee X"]')
ISSUE34 = {  # the issue's four workloads: name -> config
    "2 types, grid, 16,384": grid_config("2 types x 8192 grid", TYPES_2, range_m=8,
                                         elevation=4, yaw=8, pitch=4, roll=8),
    "2 types, grid, 102,400": grid_config("2 types x 51200 grid", TYPES_2, range_m=10,
                                          elevation=8, yaw=16, pitch=8, roll=5),
    "10 types, random, 100,000": random_config("10 types x 10000 random", TYPES_10, 10000),
    "98 types, grid, 16,464": grid_config("98 types x 168 grid", '"all"', range_m=7,
                                          elevation=2, yaw=6, pitch=2, roll=1),
}


def timed(cmd: list[str], cwd: Path, rss: list | None = None) -> float:
    """Wall seconds of ``cmd``; its peak RSS (MiB, the largest process of its tree that it
    waited for) appended to ``rss`` when given."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         text=True)
    err = p.stderr.read()
    _, status, usage = os.wait4(p.pid, 0)
    dt = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{err[-2000:]}")
    if rss is not None:
        rss.append(round(usage.ru_maxrss / 1024, 1))
    return dt


def workloads(args) -> dict:
    """Each workload's report: build and generate timed in turn, ``--repeats`` times."""
    from bench_output import write_text
    out = {}
    for name, config in ISSUE34.items():
        work = Path(tempfile.mkdtemp(prefix="apcg-gen-vs-build-"))
        try:
            cfg = work / "bench.toml"
            write_text(cfg, config)  # a fresh temporary directory of this run's own
            build = [*APCG, "dataset", "build", "--config", str(cfg), "-o", str(work / "ds"),
                     "--workers", str(args.workers)]
            timed(build, ROOT)  # fixes the conditions (and warms the file cache)
            conditions = work / "ds" / "conditions.csv"
            n = sum(1 for _ in open(conditions)) - 1
            gen = [*APCG, "generate", "--model", str(args.model), "--conditions",
                   str(conditions), "-o", str(work / "clouds.npz")]
            times: dict = {"build": [], "generate": []}
            rss: dict = {"build": [], "generate": []}
            for _ in range(args.repeats):
                shutil.rmtree(work / "ds2", ignore_errors=True)
                times["build"].append(timed([*build[:-3], str(work / "ds2"), *build[-2:]], ROOT,
                                            rss["build"]))
                (work / "clouds.npz").unlink(missing_ok=True)
                times["generate"].append(timed(gen, ROOT, rss["generate"]))
            med = {k: sorted(v)[len(v) // 2] for k, v in times.items()}
            out[name] = {"clouds": n, "seconds": times, "peak_rss_mib": rss,
                         "ms_per_cloud": {k: round(1e3 * v / n, 4) for k, v in med.items()},
                         "ratio_generate_over_build": round(med["generate"] / med["build"], 3)}
            print(name, out[name], file=sys.stderr, flush=True)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return out


def main() -> int:
    from bench_output import emit, write_text

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, help="model directory to generate with")
    ap.add_argument("--per-type", type=int, default=168)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2, help="build worker processes")
    ap.add_argument("--workloads", choices=("random-all", "issue34"), default="random-all",
                    help="random-all: every type x --per-type random conditions (default); "
                         "issue34: the issue's four workloads")
    ap.add_argument("--json")
    args = ap.parse_args()
    if args.workloads == "issue34":
        emit({"command": "python bench/generate_vs_build.py " + shlex.join(sys.argv[1:]),
              "repeats": args.repeats, "build_workers": args.workers,
              "cpu_count": os.cpu_count(), "workloads": workloads(args)}, args.json)
        return 0
    work = Path(tempfile.mkdtemp(prefix="apcg-gen-vs-build-"))
    try:
        cfg = work / "bench.toml"
        write_text(cfg, random_config(f"every type x {args.per_type} random Table-1 conditions",
                                     '"all"', args.per_type, shard=500))
        build = [*APCG, "dataset", "build", "--config", str(cfg), "-o", str(work / "ds"),
                 "--workers", str(args.workers)]
        timed(build, ROOT)  # fixes the conditions (and warms the file cache)
        conditions = work / "ds" / "conditions.csv"
        n = sum(1 for _ in open(conditions)) - 1
        gen = [*APCG, "generate", "--model", str(args.model), "--conditions", str(conditions),
               "-o", str(work / "clouds.npz")]
        times: dict = {"build": [], "generate": []}
        for _ in range(args.repeats):
            shutil.rmtree(work / "ds2", ignore_errors=True)
            times["build"].append(timed([*build[:-3], str(work / "ds2"), *build[-2:]], ROOT))
            times["generate"].append(timed(gen, ROOT))
        med = {k: sorted(v)[len(v) // 2] for k, v in times.items()}
        report = {"command": "python bench/generate_vs_build.py " + shlex.join(sys.argv[1:]),
                  "clouds": n, "repeats": args.repeats, "build_workers": args.workers,
                  "cpu_count": os.cpu_count(), "seconds": times, "median_seconds": med,
                  "ms_per_cloud": {k: round(1e3 * v / n, 4) for k, v in med.items()},
                  "ratio_generate_over_build": round(med["generate"] / med["build"], 3)}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    emit(report, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
