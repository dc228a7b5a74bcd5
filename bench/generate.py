"""APCG generation speed, end to end (noise -> generator -> DeNorm -> Im2PC -> point cloud).

    .venv/bin/python bench/generate.py [--model DIR] [--batches 1,8,32,128] [--seconds 3]

For the cpu-width network (the default model's, or a fresh one of its shape when no model is
given: the speed does not depend on the weights) and the paper's full-width network, in fp32 and
with bf16 autocast, at several batch sizes, it reports point clouds per second and the implied
time for 10^6 clouds, beside the fp32 and bf16 matmul rate this CPU reaches in the same run (the
roofline the network runs against). One process, all threads torch uses by default.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.condition import ConditionSpace, scale_ratio  # noqa: E402
from apcg_core.depth import denorm, im2pc  # noqa: E402
from apcg_core.lidar import LidarParams  # noqa: E402
from apcg_core.nn.cgan import Generator, NetConfig  # noqa: E402


def matmul_flops(dtype, n=1024, seconds=1.0) -> float:
    a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)
    a @ b
    reps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        a @ b
        reps += 1
    return 2 * n**3 * reps / (time.perf_counter() - t0)


def clouds_per_second(g, batch: int, bf16: bool, seconds: float, rng,
                      session=None) -> tuple[float, float]:
    """Clouds per second and points per cloud; through onnxruntime when ``session`` is given."""
    space = ConditionSpace()
    lidar = LidarParams()
    g.eval()

    def once():
        table = space.decode(rng.uniform(-1, 1, (batch, 6)))
        nu = space.encode(table).astype(np.float32)
        z = rng.standard_normal((batch, 100)).astype(np.float32)
        if session is not None:
            img = session.run(None, {"noise": z, "nu": nu})[0][:, 0]
        else:
            with torch.no_grad(), torch.autocast("cpu", torch.bfloat16, enabled=bf16):
                img = g(torch.from_numpy(z), torch.from_numpy(nu)).float()[:, 0].numpy()
        d = denorm(img, scale_ratio(table[:, 1]))
        cloud = im2pc(d, table[:, 1], table[:, 2], 40.0, lidar)
        return len(cloud)

    once()
    n, pts, t0 = 0, 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        pts += once()
        n += batch
    dt = time.perf_counter() - t0
    return n / dt, pts / max(n, 1)


def main() -> int:
    from bench_output import emit

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", help="model directory (its network width is used)")
    ap.add_argument("--batches", default="1,8,32,128")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--json")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    nets = {}
    if args.model:
        from apcg_core.families.cgan import APCGModel
        nets["model"] = APCGModel(args.model, runtime="torch").torch_generator()
    else:
        torch.manual_seed(0)
        nets["cpu-width (0.25)"] = Generator(NetConfig(width=0.25))
    torch.manual_seed(0)
    nets["paper full width (1.0)"] = Generator(NetConfig(width=1.0))
    res = {"command": "python bench/generate.py " + shlex.join(sys.argv[1:]),
           "threads": torch.get_num_threads(), "cpus": os.cpu_count(),
           "matmul_gflops_fp32": round(matmul_flops(torch.float32) / 1e9, 1),
           "matmul_gflops_bf16": round(matmul_flops(torch.bfloat16) / 1e9, 1), "rows": []}
    import tempfile

    from apcg_core.families.base import onnxruntime
    from training.export import export_onnx
    ort = onnxruntime()  # its usage telemetry off, as the package runs it
    for name, g in nets.items():
        with tempfile.TemporaryDirectory() as tmp:
            export_onnx(g, Path(tmp) / "g.onnx")
            session = ort.InferenceSession(str(Path(tmp) / "g.onnx"),
                                           providers=["CPUExecutionProvider"])
        for runtime, bf16 in (("torch", False), ("torch", True), ("onnxruntime", False)):
            for b in (int(x) for x in args.batches.split(",")):
                cps, ppc = clouds_per_second(g, b, bf16, args.seconds, rng,
                                             session if runtime == "onnxruntime" else None)
                row = {"network": name, "runtime": runtime,
                       "dtype": "bf16" if bf16 else "fp32", "batch": b,
                       "clouds_per_s": round(cps, 1), "points_per_cloud": round(ppc, 1),
                       "time_for_1e6_clouds_min": round(1e6 / cps / 60, 1)}
                res["rows"].append(row)
                print(json.dumps(row), flush=True)
    print(json.dumps({k: v for k, v in res.items() if k != "rows"}))
    emit(res, args.json, show=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
