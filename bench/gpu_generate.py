"""The default generator's throughput on one device, against the paper's Fig. 18 (10^6 clouds in
under 6 s on its GPU).

    python bench/gpu_generate.py [--model DIR] [--device cuda] [--sizes 10000,100000,1000000]
                                 [--dtype fp32,bf16] [--lidar PRESET|FILE] [--json OUT.json]

For each of Fig. 18's four workloads (2, 4 and 8 aircraft types with equal counts, 8 types
with random counts) and each size N, it times condition table -> point clouds on the device:
random conditions of the model's condition space (no two share an attitude, so nothing is
reused across clouds), nu encoded on the CPU, the APCG+ network (torch, the model's own
weights) drawing the sheets in batches, and the clouds read off the sheets in place
(``apcg_core.nn.apcg_plus.read_clouds``: every box cell, float64 geometry, the model's draw).
The clouds stay on
the device, as Fig. 18's did; copying them back would be the next cost. The time is wall
clock from the numpy table to the last point, synchronised, after one warm-up of the first
size. Before timing, the device reader is checked against the CPU reader the package uses
(PlusModel.clouds_of) on 512 conditions: the same cells, ranges within 1e-6 m.

Also on the CPU of the same machine for reference, when ``--cpu-reference N`` > 0: the package's
own path (onnxruntime + numpy reader, all cores), ``PlusModel.generate`` on N conditions.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.families import load_model  # noqa: E402
from apcg_core.families.apcg_plus import box_half_cells  # noqa: E402
from apcg_core.lidar import load_lidar  # noqa: E402
from apcg_core.nn.apcg_plus import read_clouds  # noqa: E402

BATCH = 4096  # conditions per network call on the device


def workloads(model, rng) -> dict:
    """Fig. 18's four sets of types: the first 2, 4, 8 aircraft of the model's table (equal
    counts) and 8 with random counts (Dirichlet shares)."""
    drones = set(model.space.drone_types)
    aircraft = [i for i in range(len(model.types.names)) if i not in drones]
    shares = rng.dirichlet(np.ones(8))
    return {"2 types": (aircraft[:2], None), "4 types": (aircraft[:4], None),
            "8 types": (aircraft[:8], None), "8 types, random counts": (aircraft[:8], shares)}


def condition_table(model, codes, shares, n, rng) -> np.ndarray:
    """n random conditions (model codes): every pose drawn uniformly in the model's space."""
    if shares is None:
        code = np.repeat(np.asarray(codes), -(-n // len(codes)))[:n]
    else:
        code = rng.choice(np.asarray(codes), size=n, p=shares)
    nu = rng.uniform(-1.0, 1.0, (n, 6))
    table = model.space.decode(nu)
    table[:, 0] = code
    lo, hi = model.space.bounds(table)  # the range band of each row's own type
    table[:, 1] = lo[:, 1] + (nu[:, 1] + 1.0) / 2.0 * (hi[:, 1] - lo[:, 1])
    return table


class DeviceGenerator:
    def __init__(self, model, device: str, dtype: str) -> None:
        self.model = model
        self.device = torch.device(device)
        self.net = model._open("torch").net.to(self.device)
        self.autocast = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}[dtype]

    def sheets(self, table: np.ndarray) -> torch.Tensor:
        nu = torch.from_numpy(self.model.space.encode(table).astype(np.float32))
        codes = torch.from_numpy(table[:, 0].astype(np.int64))
        out = []
        with torch.no_grad():
            for s in range(0, len(table), BATCH):
                c = codes[s:s + BATCH].to(self.device, non_blocking=True)
                p = nu[s:s + BATCH, 1:].to(self.device, non_blocking=True)
                if self.autocast is None:
                    out.append(self.net(c, p))
                else:
                    with torch.autocast(self.device.type, self.autocast):
                        out.append(self.net(c, p).float())
        return torch.cat(out)

    def clouds(self, table: np.ndarray):
        m = self.model
        rad = m.radius[table[:, 0].astype(np.int64)]
        box = box_half_cells(table[:, 1], table[:, 2], rad, m.lidar)
        points, n = 0, 0
        for s in range(0, len(table), 8 * BATCH):  # sheets of 32 K conditions at a time
            part = table[s:s + 8 * BATCH]
            sh = self.sheets(part)
            got = read_clouds(sh, part[:, 1], part[:, 2], rad[s:s + 8 * BATCH],
                              (box[0][s:s + 8 * BATCH], box[1][s:s + 8 * BATCH]), m.lidar,
                              m.tau, m.quantize, m.draw)
            points += int(got[0].shape[0])
            n += len(part)
        return points

    def sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize()


def check_reader(model, gen: DeviceGenerator, rng) -> dict:
    """The device reader against the package's CPU reader on the same (fp32) sheets."""
    table = condition_table(model, list(range(len(model.types.names))), None, 512, rng)
    sheets = gen.sheets(table)
    rad = model.radius[table[:, 0].astype(np.int64)]
    box = box_half_cells(table[:, 1], table[:, 2], rad, model.lidar)
    xyz, r, w, h, sample = (t.cpu().numpy() for t in read_clouds(
        sheets, table[:, 1], table[:, 2], rad, box, model.lidar, model.tau, model.quantize,
        model.draw))
    ref = model.clouds_of(table, sheets.float().cpu().numpy())
    same = (len(r) == len(ref.range_m) and (w == ref.cell_w).all() and (h == ref.cell_h).all()
            and (sample == ref.sample).all())
    diff = float(np.abs(r - ref.range_m).max()) if same and len(r) else None
    return {"conditions": 512, "points_device": int(len(r)), "points_cpu": int(len(ref.range_m)),
            "same_cells": bool(same), "max_range_diff_m": diff}


def main() -> int:
    from bench_output import emit

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default=None, help="model directory (default: the shipped one)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--sizes", default="10000,100000,1000000")
    ap.add_argument("--dtype", default="fp32,bf16", help="network precision(s): fp32, bf16, fp16")
    ap.add_argument("--cpu-reference", type=int, default=0,
                    help="also time the package's CPU path on this many conditions")
    ap.add_argument("--lidar", help="a lidar preset or file (default: the model's own)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json")
    args = ap.parse_args()
    model = load_model(args.model)
    if args.lidar:
        model.use_lidar(load_lidar(args.lidar))
    rng = np.random.default_rng(args.seed)
    sizes = [int(x) for x in args.sizes.split(",")]
    machine = {"device": args.device, "torch": torch.__version__, "numpy": np.__version__,
               "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count()}
    if args.device.startswith("cuda"):
        p = torch.cuda.get_device_properties(0)
        machine.update(gpu=p.name, gpu_memory_gib=round(p.total_memory / 2**30, 1),
                       multiprocessors=p.multi_processor_count)
    print(json.dumps(machine), flush=True)
    report = {"machine": machine, "model": str(model.directory), "runs": [],
              "lidar": {"width": model.lidar.width, "height": model.lidar.height}}
    for dtype in args.dtype.split(","):
        gen = DeviceGenerator(model, args.device, dtype)
        check = check_reader(model, gen, rng)
        print(dtype, "reader check", json.dumps(check), flush=True)
        report.setdefault("reader_check", {})[dtype] = check
        for name, (codes, shares) in workloads(model, rng).items():
            warm = condition_table(model, codes, shares, min(sizes), rng)
            gen.clouds(warm)
            gen.sync()
            for n in sizes:
                table = condition_table(model, codes, shares, n, rng)
                gen.sync()
                t0 = time.perf_counter()
                points = gen.clouds(table)
                gen.sync()
                dt = time.perf_counter() - t0
                row = {"dtype": dtype, "workload": name, "clouds": n, "seconds": round(dt, 4),
                       "clouds_per_s": round(n / dt), "points_per_cloud": round(points / n, 1),
                       "seconds_per_1e6": round(dt * 1e6 / n, 3)}
                if args.device.startswith("cuda"):
                    row["peak_gpu_mib"] = round(torch.cuda.max_memory_allocated() / 2**20)
                print(json.dumps(row), flush=True)
                report["runs"].append(row)
    if args.cpu_reference > 0:
        table = condition_table(model, list(range(8)), None, args.cpu_reference, rng)
        conditions = model.conditions([model.types.names[int(c)] for c in table[:, 0]],
                                      table[:, 1:])
        model.generate(conditions[:256] if hasattr(conditions, "__getitem__") else conditions)
        t0 = time.perf_counter()
        res = model.generate(conditions)
        dt = time.perf_counter() - t0
        row = {"cpu_reference": True, "clouds": args.cpu_reference, "seconds": round(dt, 3),
               "clouds_per_s": round(args.cpu_reference / dt),
               "points_per_cloud": round(len(res.cloud.range_m) / args.cpu_reference, 1),
               "threads": model.workers}
        print(json.dumps(row), flush=True)
        report["cpu_reference"] = row
    emit(report, args.json, show=False)  # the JSON rows were printed as they came
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
