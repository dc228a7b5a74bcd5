"""Build a dataset: plan -> shards (one type each) -> manifest. Resumable and deterministic.

A shard's file appears under its final name only when complete (written to a ``.part`` file,
fsynced, renamed), so a build killed at any point and started again skips the finished shards
and remakes the rest; since every shard is a pure function of the plan, the result is byte for
byte the dataset of an uninterrupted run.

Builds of different ``--shard I/N`` parts may run at once into one directory (a job array):
every temporary file carries its writer's pid, files that several processes write (the plan
files, the manifest) have the same bytes whoever writes them and appear by atomic rename, and
a lock file per shard spec refuses a second build of the same part while the first one lives.
"""

from __future__ import annotations

import os
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from apcg_core import __version__
from apcg_core.depth import DEPTH_SCALE, TARGET_FLOOR
from apcg_core.errors import InputError
from apcg_core.io.dataset import (
    FORMAT_VERSION,
    Shard,
    json_bytes,
    read_header,
    sha256_file,
    write_atomic,
)
from apcg_core.lidar import DEG
from apcg_core.progress import Progress

from .backends import check_backend
from .plan import Plan, ShardPlan, load_config, make_plan
from .rays import bounding_radius


def header_of(plan: Plan, catalog) -> dict:
    cfg = plan.config
    return {
        "format": "apcg-dataset", "format_version": FORMAT_VERSION, "apcg_version": __version__,
        "name": cfg.get("name", ""), "config": cfg, "lidar": plan.lidar.to_dict(),
        "condition_space": plan.space.to_dict(),
        "types": [{"code": i, "name": t.name, "catalog_index": t.index, "kind": t.kind,
                   "range_band": t.range_band, "depth_length_m": catalog.depth_length_m(t),
                   "bounding_radius_m": bounding_radius(catalog.mesh(t).vertices)}
                  for i, t in enumerate(plan.types)],
        "n_samples": plan.n_samples,
        "n_train": int((plan.split == "train").sum()), "n_test": int((plan.split == "test").sum()),
        "grid_values": plan.values,
        "shards": [{"index": s.index, "file": s.file, "split": s.split, "type_code": s.type_code,
                    "n_samples": len(s.rows)} for s in plan.shards],
        "conditions_file": "conditions.csv",
    }


def conditions_csv(plan: Plan) -> bytes:
    shard_of = np.empty(plan.n_samples, np.int64)
    for s in plan.shards:
        shard_of[s.rows] = s.index
    t = plan.table
    names = [ty.name.replace(",", " ") for ty in plan.types]
    lines = ["sample_id,split,shard,type_code,type_name,range_m,elevation_deg,pitch_deg,"
             "yaw_deg,roll_deg"]
    deg = t[:, 2:] / DEG
    for i in range(plan.n_samples):
        c = int(t[i, 0])
        lines.append(f"{i},{plan.split[i]},{shard_of[i]},{c},{names[c]},{t[i, 1]!r},"
                     f"{deg[i, 0]!r},{deg[i, 1]!r},{deg[i, 2]!r},{deg[i, 3]!r}")
    return ("\n".join(lines) + "\n").encode()


@dataclass
class ShardTask:
    """What a worker needs for one shard (small and picklable: no plan, no catalog)."""

    index: int
    path: str
    type_catalog_index: int
    depth_length_m: float
    rows: np.ndarray
    table: np.ndarray
    nu: np.ndarray
    backend: str
    quantize: bool
    supersample: int
    fine_cloud_points: int
    lidar: dict


_SIMULATORS: dict = {}


def _simulator(task: ShardTask):
    from apcg_core.lidar import LidarParams

    from .simulate import Simulator
    key = (task.backend, task.quantize, task.supersample, task.fine_cloud_points,
           tuple(sorted(task.lidar.items())))
    if key not in _SIMULATORS:
        _SIMULATORS[key] = Simulator(task.backend, LidarParams.from_dict(task.lidar),
                                     task.quantize, task.supersample, task.fine_cloud_points)
    return _SIMULATORS[key]


def close_simulators() -> None:
    """Free every cached simulator's backend (Blender objects must go before Blender exits)."""
    for sim in _SIMULATORS.values():
        sim.close()
    _SIMULATORS.clear()


def compute_shard(task: ShardTask) -> Shard:
    from apcg_core.catalog.catalog import default_catalog
    sim = _simulator(task)
    lidar = sim.lidar
    cl = sim.simulate_cells_type(default_catalog(), task.type_catalog_index, task.table)
    n = len(task.rows)
    s = cl.sample
    if len(s) > 1 and (np.diff(s) < 0).any():  # backends return clouds in sample order
        raise RuntimeError("internal error: simulator output is not grouped by sample")
    counts = np.bincount(s, minlength=n)
    r0 = task.table[s, 1]
    d = DEPTH_SCALE * (cl.range_m - r0) / task.depth_length_m
    dc = np.clip(d, TARGET_FLOOR, 1.0)
    pixel = lidar.row_of_h(cl.cell_h) * lidar.width + lidar.col_of_w(cl.cell_w)
    pix_type = np.uint16 if lidar.width * lidar.height <= 1 << 16 else np.uint32
    return Shard(sample_id=task.rows.astype(np.int64), conditions=task.table,
                 nu=task.nu.astype(np.float32),
                 offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
                 pixel=pixel.astype(pix_type), depth=dc.astype(np.float16),
                 delta_range_m=(cl.range_m - r0).astype(np.float32),
                 clipped=cl.clipped.astype(bool),
                 n_clamped=np.bincount(s, weights=(d != dc), minlength=n).astype(np.int32),
                 n_rays=cl.n_rays.astype(np.int32))


def worker_init() -> None:
    """Pool initializer. A spawned child inherits its parent's sys.path; once the parent has
    imported the bpy module that includes Blender's own scripts/modules folder, whose ``bpy``
    package would then shadow the bpy extension module in the child. Drop those entries."""
    marker = f"{os.sep}bpy{os.sep}"
    sys.path[:] = [p for p in sys.path if not (marker in p and f"{os.sep}scripts" in p)]


def _part_suffix() -> str:
    """Temporary-file suffix unique to this process (concurrent builders share a directory)."""
    return f".{os.getpid()}.part"


def run_task(task: ShardTask) -> tuple[int, int, float]:
    t0 = time.perf_counter()
    shard = compute_shard(task)
    path = Path(task.path)
    write_atomic(path, shard.to_bytes(), part_suffix=_part_suffix())
    return task.index, len(task.rows), time.perf_counter() - t0


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


class ShardLock:
    """``DIR/.build-I-of-N.lock``, created with O_EXCL, holding "pid host": one live build per
    shard spec and directory. A lock whose process is gone (same host) is taken over."""

    def __init__(self, out: Path, part_i: int, part_n: int) -> None:
        self.path = out / f".build-{part_i}-of-{part_n}.lock"
        self.spec = f"{part_i}/{part_n}"
        self.mine = f"{os.getpid()} {socket.gethostname()}\n"
        self.held = False

    def acquire(self) -> None:
        for _ in range(10):
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                self._take_over_if_stale()
                continue
            with os.fdopen(fd, "w") as f:
                f.write(self.mine)
            self.held = True
            return
        raise InputError(f"could not take the lock {self.path}; delete it if no build of "
                         f"--shard {self.spec} runs")

    def _take_over_if_stale(self) -> None:
        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return  # its owner just finished: try again
        pid, host = _lock_owner(text)
        if pid is None or host != socket.gethostname() or _pid_alive(pid):
            who = f"pid {pid} on {host}" if pid is not None else "an unreadable lock"
            raise InputError(
                f"another build of --shard {self.spec} into {self.path.parent} is running "
                f"({who}, lock file {self.path}); wait for it to finish, or stop it, or delete "
                "the lock file if that process is gone")
        # Dead owner on this host: move its lock aside atomically (only one taker wins), check
        # that what we moved is still the dead one's, then create ours on the next round.
        aside = self.path.with_name(self.path.name + f".stale.{os.getpid()}")
        try:
            os.rename(self.path, aside)
        except FileNotFoundError:
            return
        if aside.read_text() != text:  # a live taker replaced it meanwhile: give it back
            try:
                os.link(aside, self.path)
            except FileExistsError:
                pass
        aside.unlink()

    def release(self) -> None:
        if self.held:
            try:
                if self.path.read_text() == self.mine:
                    self.path.unlink()
            except FileNotFoundError:
                pass
            self.held = False


def _lock_owner(text: str) -> tuple[int | None, str | None]:
    parts = text.split()
    if len(parts) != 2 or not parts[0].isdigit():
        return None, None
    return int(parts[0]), parts[1]


def _remove_dead_parts(directory: Path) -> None:
    """Delete ``NAME.PID.part`` files whose writer is gone (or is us); never a live writer's."""
    for part in directory.glob("*.part"):
        pid = part.name.rsplit(".", 2)[-2] if part.name.count(".") >= 2 else ""
        if not pid.isdigit() or int(pid) == os.getpid() or not _pid_alive(int(pid)):
            try:
                part.unlink()
            except FileNotFoundError:
                pass


def parse_shard_spec(spec: str | None) -> tuple[int, int]:
    if spec is None:
        return 0, 1
    try:
        i, n = (int(x) for x in spec.split("/"))
    except ValueError as exc:
        raise InputError(f"--shard takes I/N (e.g. 3/10), got {spec!r}") from exc
    if n < 1 or not 0 <= i < n:
        raise InputError(f"--shard {spec}: need N >= 1 and 0 <= I < N (I counts from 0)")
    return i, n


def build_dataset(config: str | dict, out_dir, backend: str | None = None, workers: int = 1,
                  shard_spec: str | None = None, progress: bool = True,
                  tasks_per_process: int | None = None, catalog=None) -> dict:
    """Build (or resume) the dataset of ``config`` in ``out_dir``; returns a summary."""
    from apcg_core.catalog.catalog import default_catalog
    catalog = catalog or default_catalog()
    cfg = load_config(config) if isinstance(config, str) else dict(config)
    if backend:
        check_backend(backend)
    plan = make_plan(cfg, catalog, backend)
    check_backend(plan.config["backend"])
    if not isinstance(workers, int) or workers < 1:
        raise InputError(f"--workers must be an integer >= 1, got {workers!r}")
    part_i, part_n = parse_shard_spec(shard_spec)
    out = Path(out_dir)
    (out / "shards").mkdir(parents=True, exist_ok=True)
    lock = ShardLock(out, part_i, part_n)
    lock.acquire()
    try:
        return _build_locked(plan, catalog, out, workers, part_i, part_n, progress,
                             tasks_per_process)
    finally:
        lock.release()


def _build_locked(plan: Plan, catalog, out: Path, workers: int, part_i: int, part_n: int,
                  progress: bool, tasks_per_process: int | None) -> dict:
    header = json_bytes(header_of(plan, catalog))
    head_path = out / "dataset.json"
    # Concurrent builders of one plan write the same bytes here, each through its own
    # temporary file and an atomic rename, so any interleaving leaves complete, equal files.
    if head_path.exists():
        if head_path.read_bytes() != header:
            raise InputError(f"{out} already holds a different dataset (its dataset.json differs "
                             "from this config's); build into a new directory or delete it")
    else:
        write_atomic(out / "conditions.csv", conditions_csv(plan), part_suffix=_part_suffix())
        # last: its presence means the plan files are complete
        write_atomic(head_path, header, part_suffix=_part_suffix())
    if not (out / "conditions.csv").exists():
        write_atomic(out / "conditions.csv", conditions_csv(plan), part_suffix=_part_suffix())

    mine = [s for s in plan.shards if s.index % part_n == part_i]
    todo = [s for s in mine if not (out / s.file).exists()]
    done_samples = sum(len(s.rows) for s in mine) - sum(len(s.rows) for s in todo)
    tasks = [_task(plan, catalog, s, out) for s in todo]
    bar = Progress(sum(len(s.rows) for s in mine), "sample", progress, done=done_samples)
    t0 = time.perf_counter()
    try:
        if workers == 1 and not (plan.config["backend"].startswith("blender")
                                 and tasks_per_process):
            for task in tasks:
                bar.update(run_task(task)[1])
        else:
            per = tasks_per_process
            if per is None and plan.config["backend"].startswith("blender"):
                per = 1  # one process per shard: Blender's memory grows across long loops
            # Imported only here: Debian's Blender 3.4 crashes at exit once multiprocessing has
            # been imported, and inside a Blender binary builds run with one worker.
            import multiprocessing as mp
            ctx = mp.get_context("spawn")
            with ctx.Pool(workers, initializer=worker_init, maxtasksperchild=per) as pool:
                for _, n, _ in pool.imap_unordered(run_task, tasks):
                    bar.update(n)
    finally:
        close_simulators()
        bar.close()
    elapsed = time.perf_counter() - t0
    complete = all((out / s.file).exists() for s in plan.shards)
    if complete:
        _remove_dead_parts(out / "shards")
        _remove_dead_parts(out)
        manifest = {"complete": True, "shards": [
            {"file": s.file, "sha256": sha256_file(out / s.file)} for s in plan.shards]}
        write_atomic(out / "manifest.json", json_bytes(manifest), part_suffix=_part_suffix())
    return {"directory": str(out), "built_shards": len(tasks), "skipped_shards": len(mine) -
            len(tasks), "samples_built": sum(len(t.rows) for t in tasks),
            "seconds": round(elapsed, 3), "complete": complete}


def _task(plan: Plan, catalog, s: ShardPlan, out: Path) -> ShardTask:
    t = plan.types[s.type_code]
    table = plan.table[s.rows]
    return ShardTask(index=s.index, path=str(out / s.file), type_catalog_index=t.index,
                     depth_length_m=catalog.depth_length_m(t), rows=s.rows, table=table,
                     nu=plan.space.encode(table), backend=plan.config["backend"],
                     quantize=bool(plan.config.get("quantize", True)),
                     supersample=int(plan.config.get("supersample", 1)),
                     fine_cloud_points=int(plan.config.get("fine_cloud_points", 10_000)),
                     lidar=plan.lidar.to_dict())


def dataset_info(directory, verify: bool = False, require_complete: bool = False) -> dict:
    """Summary of a dataset directory; ``verify`` loads every shard and checks its hash;
    ``require_complete`` raises unless every shard and the manifest are there."""
    out = Path(directory)
    head = read_header(out)
    shards = head["shards"]
    present = [s for s in shards if (out / s["file"]).exists()]
    if require_complete and (len(present) < len(shards)
                             or not (out / "manifest.json").exists()):
        raise InputError(f"dataset {out} is not complete: {len(present)} of {len(shards)} "
                         "shards present; run the same `apcg dataset build` again to finish it")
    info = {"directory": str(out), "name": head["name"], "format_version": head["format_version"],
            "backend": head["config"].get("backend"), "n_types": len(head["types"]),
            "n_samples": head["n_samples"], "n_train": head["n_train"], "n_test": head["n_test"],
            "shards_total": len(shards), "shards_present": len(present),
            "complete": (out / "manifest.json").exists() and len(present) == len(shards),
            "bytes_on_disk": sum((out / s["file"]).stat().st_size for s in present)}
    n_done = sum(s["n_samples"] for s in present)
    info["samples_present"] = n_done
    if verify:
        import json
        manifest = (json.loads((out / "manifest.json").read_text())
                    if (out / "manifest.json").exists() else {"shards": []})
        sums = {m["file"]: m["sha256"] for m in manifest["shards"]}
        n_points = clipped = clamped = empty = 0
        bad = []
        for s in present:
            p = out / s["file"]
            if sums.get(s["file"]) not in (None, sha256_file(p)):
                bad.append(s["file"])
                continue
            sh = Shard.load(p)
            if len(sh) != s["n_samples"]:
                bad.append(s["file"])
                continue
            n_points += len(sh.pixel)
            clipped += int(sh.clipped.sum())
            clamped += int(sh.n_clamped.sum())
            empty += int((np.diff(sh.offsets) == 0).sum())
        if bad:
            raise InputError(f"corrupt shards in {out}: {bad}; delete them and run the build "
                             "again to remake them")
        info.update({"points": n_points, "mean_points_per_sample": n_points / max(n_done, 1),
                     "clipped_samples": clipped, "clamped_pixels": clamped,
                     "empty_samples": empty, "verified": True})
    return info
