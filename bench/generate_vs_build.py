"""Generation against exact simulation, whole commands, on the same conditions, in one run.

    .venv/bin/python bench/generate_vs_build.py --model DIR [--per-type 168] [--repeats 3]
        [--workers 2] [--json bench/results/generate_vs_build.json]

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
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
APCG = [sys.executable, "-m", "apcg_core.cli"]

CONFIG = """description = "bench: every type x {n} random Table-1 conditions"
seed = 11
backend = "embree"
shard_size = 500
test_fraction = 0.2
quantize = true
supersample = 1
sampling = "random"
samples_per_type = {n}
types = "all"
"""


def timed(cmd: list[str], cwd: Path) -> float:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{r.stderr[-2000:]}")
    return dt


def main() -> int:
    from bench_output import emit

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, help="model directory to generate with")
    ap.add_argument("--per-type", type=int, default=168)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2, help="build worker processes")
    ap.add_argument("--json")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="apcg-gen-vs-build-"))
    try:
        cfg = work / "bench.toml"
        cfg.write_text(CONFIG.format(n=args.per_type))
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
        report = {"command": "python bench/generate_vs_build.py " + " ".join(sys.argv[1:]),
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
