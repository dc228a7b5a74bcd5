"""Where `apcg generate --conditions` spends its time, per cloud, stage by stage.

    .venv/bin/python bench/generate_profile.py --conditions FILE.csv [--model DIR] [--n 8192]
        [--chunks 256,1024] [--json bench/results/generate_profile.json]

One process, one thread, in the order the command runs them (start-up is timed as whole
processes): start-up (`apcg generate` of one condition, a fresh process, minus nothing: what
every run pays once), reading the CSV (the whole file), the window check, the network
(``model.sheets``, the ONNX session on one thread, at each network batch size of
``--chunks``), reading the clouds off its output
(``model.clouds_of``; its compiled kernels loaded first unless ``APCG_KERNELS=numpy``, as
a long run has them) and writing them (``CloudWriter``, NPZ and PLY, into a temporary
directory). CPU seconds of this process (``time.process_time``) are the figure: the machine is
shared, and other jobs move wall time far more than CPU time; wall is reported beside them.
The first ``--n`` conditions of the file are generated (read whole for the CSV stage).
"""

from __future__ import annotations

import argparse
import os
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
# Two lanes, as `apcg generate` runs on this machine: each network call on one onnxruntime
# thread. The bench calls no lanes, so every stage runs on one thread: CPU per cloud of each.
# (APCG_THREADS=1 opens onnxruntime with its own pool: the network's CPU about twice its wall.)
os.environ.setdefault("APCG_THREADS", "2")

import numpy as np  # noqa: E402


class Clock:
    def __init__(self) -> None:
        self.cpu, self.wall = time.process_time(), time.perf_counter()

    def read(self, n: int) -> dict:
        return {"cpu_ms_per_cloud": round(1e3 * (time.process_time() - self.cpu) / n, 4),
                "wall_ms_per_cloud": round(1e3 * (time.perf_counter() - self.wall) / n, 4)}


def start_up(model, repeats: int = 3) -> dict:
    """A whole `apcg generate` of one condition: the cost every run pays once."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "apcg_core.cli", "generate", "--type", "A320neo",
               "--range-m", "5000", "--elevation-deg", "3.5", "--pitch-deg", "2", "--force",
               "-o", str(Path(tmp) / "one.npz")]
        if model:
            cmd += ["--model", str(model)]
        cpu, wall = [], []
        for _ in range(repeats):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, capture_output=True, cwd=ROOT, env=os.environ)
            wall.append(time.perf_counter() - t0)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu.append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
    return {"cpu_s": round(float(np.median(cpu)), 3), "wall_s": round(float(np.median(wall)), 3)}


def main() -> int:
    from bench_output import emit

    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.families import conditions_from_csv, load_model
    from apcg_core.io.clouds import CloudWriter

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--conditions", required=True)
    ap.add_argument("--model", help="model directory (default: the shipped default model)")
    ap.add_argument("--n", type=int, default=8192, help="clouds generated (the first rows)")
    ap.add_argument("--chunks", default="256,1024", help="network batch sizes to time")
    ap.add_argument("--json")
    args = ap.parse_args()
    rows = {}
    rows["start_up"] = start_up(args.model)
    model = load_model(args.model)
    c = Clock()
    conditions = conditions_from_csv(args.conditions, model)
    rows["csv"] = c.read(len(conditions)) | {"rows": len(conditions)}
    from apcg_core.generation_cli import _warn_window
    from apcg_core.plausibility import WINDOW_CHECK_ROWS
    default_catalog().mesh(conditions.names[0])  # the catalog's modules and first mesh loaded
    c = Clock()
    _warn_window(model, conditions)  # what every request pays once: its first rows' window
    rows["window_check"] = c.read(1) | {"rows": min(len(conditions), WINDOW_CHECK_ROWS)}
    table = model.repeated_conditions(conditions[:args.n], 1)
    n = len(table)
    model.sheets(table[:64])  # the session opened, its arena warmed
    sheets = None
    for chunk in (int(x) for x in args.chunks.split(",")):
        c = Clock()
        parts = [model.sheets(table[s:s + chunk], rows=chunk) for s in range(0, n, chunk)]
        rows[f"network_chunk_{chunk}"] = c.read(n)
        sheets = np.concatenate(parts)
    from apcg_core.families import plus_kernels
    from apcg_core.families.apcg_plus import CHUNK
    if plus_kernels.enabled():  # loaded, as a run has them after its first SWITCH_CLOUDS
        plus_kernels.require()
    model.clouds_of(table[:CHUNK], sheets[:CHUNK])  # the reader's code read before the clock
    c = Clock()
    clouds = []
    for s in range(0, n, CHUNK):
        cloud = model.clouds_of(table[s:s + CHUNK], sheets[s:s + CHUNK])
        cloud.sample = cloud.sample + s
        clouds.append(cloud)
    rows["read_clouds"] = c.read(n) | {
        "points_per_cloud": round(sum(len(x) for x in clouds) / n, 1)}
    with tempfile.TemporaryDirectory() as tmp:
        for ext in ("npz", "ply"):
            c = Clock()
            with CloudWriter(Path(tmp) / f"out.{ext}", {"bench": True}) as w:
                for cloud in clouds:
                    w.write(cloud)
            rows[f"write_{ext}"] = c.read(n)
    report = {"command": "python bench/generate_profile.py " + shlex.join(sys.argv[1:]),
              "model": str(model.directory), "family": model.family, "clouds": n,
              "threads": 1, "cpu_count": os.cpu_count(), "load_avg": os.getloadavg()[0],
              "compiled_reader": plus_kernels.loaded(),
              "stages": rows}
    emit(report, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
