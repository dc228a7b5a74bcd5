"""One shard: the small task a worker is handed, and the pure function that computes the shard
and writes it whole (``run_task``). Every engine (``engine.py``) runs ``run_task`` on the tasks
that ``build.py`` plans, in this process, a local pool or a Dask cluster; a worker keeps its
simulators across tasks until ``close_simulators``.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from apcg_core.depth import DEPTH_SCALE, TARGET_FLOOR
from apcg_core.io.dataset import Shard, write_atomic
from apcg_core.testpoints import wait_point


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
    sensor: dict | None = None  # SensorParams.to_dict(); None: the ideal standard cloud
    seed: int = 0  # the dataset's seed: a sample's photons are seeded by (seed, sample id)
    incidence: bool = False  # also each return's cosine of incidence (cos_incidence)
    # the dataset's stamp (apcg_core.io.dataset.dataset_stamp of its header), recorded in the
    # shard; None: none recorded (benches' loose shards)
    dataset: str | None = None


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
    if task.sensor is not None:
        shard = _photon_shard(task, sim, default_catalog())
    else:
        cl = sim.simulate_cells_type(default_catalog(), task.type_catalog_index, task.table)
        shard = _shard(task, lidar, cl.sample, cl.cell_w, cl.cell_h, cl.range_m, cl.clipped,
                       cl.n_rays)
        if task.incidence:
            shard.cos_incidence = _incidence(sim, default_catalog(), task,
                                             cl).astype(np.float16)
    shard.dataset = task.dataset  # which dataset it is (checked by every reader and resume)
    return shard


def _incidence(sim, catalog, task: ShardTask, cl) -> np.ndarray:
    """Each return's cosine of incidence: that of the nearest of its cell's sub-rays (the ray
    whose range the cell returns), from the same rays cast again with their faces named
    (``Simulator.sub_ray_hits``). A return whose cell the second cast misses (float32 rounding
    on an edge between two casts, rare) is taken as facing the lidar, as the photon stage
    takes a hit whose face the caster cannot name."""
    t = catalog.get(task.type_catalog_index)
    hits = sim.sub_ray_hits(catalog.mesh(t), task.table, key=("type", t.index))
    span = np.int64(1) << 20

    def key(s, w, h):
        return ((s.astype(np.int64) * span + h.astype(np.int64) + span // 2) * span
                + w.astype(np.int64) + span // 2)

    k = key(hits.sample, hits.w, hits.h)
    order = np.lexsort((hits.range_m, k))  # by cell, nearest sub-ray first
    k, cos = k[order], hits.cos[order]
    first = np.concatenate([[True], k[1:] != k[:-1]]) if len(k) else np.zeros(0, bool)
    k, cos = k[first], cos[first]
    want = key(cl.sample, cl.cell_w, cl.cell_h)
    at = np.minimum(np.searchsorted(k, want), max(len(k) - 1, 0))
    found = (k[at] == want) if len(k) else np.zeros(len(want), bool)
    return np.where(found, cos[at] if len(k) else 1.0, 1.0)


def _pixels(lidar, w, h):
    pix_type = np.uint16 if lidar.width * lidar.height <= 1 << 16 else np.uint32
    return (lidar.row_of_h(h) * lidar.width + lidar.col_of_w(w)).astype(pix_type)


def _photon_shard(task: ShardTask, sim, catalog) -> Shard:
    """A shard of what the sensor records: the photon points (or events: nearest of a pixel
    last, so the depth image holds the first return), their labels and counts, and per target
    cell the expected signal per pulse."""
    from apcg_core.sensor import sensor_from_table
    sensor = sensor_from_table(task.sensor)
    cells, clipped, n_rays = sim.photon_cells_type(catalog, task.type_catalog_index, task.table,
                                                   sensor, task.seed, sample_ids=task.rows)
    pixel = _pixels(sim.lidar, cells.w, cells.h)
    order = np.lexsort((-cells.range_m, pixel, cells.sample))
    shard = _shard(task, sim.lidar, cells.sample[order], cells.w[order], cells.h[order],
                   cells.range_m[order], clipped, n_rays)
    n = len(task.rows)
    shard.label = cells.label[order]
    shard.count = cells.count[order]
    if sensor.output == "events":
        shard.pulse = cells.pulse[order]
    shard.target_offsets = np.concatenate(
        [[0], np.cumsum(np.bincount(cells.target_sample, minlength=n))]).astype(np.int64)
    shard.target_pixel = _pixels(sim.lidar, cells.target_w, cells.target_h)
    shard.target_signal_pe = cells.target_signal_pe.astype(np.float32)
    return shard


def _shard(task: ShardTask, lidar, s, cell_w, cell_h, range_m, clipped, n_rays) -> Shard:
    n = len(task.rows)
    if len(s) > 1 and (np.diff(s) < 0).any():  # backends return clouds in sample order
        raise RuntimeError("internal error: simulator output is not grouped by sample")
    counts = np.bincount(s, minlength=n)
    r0 = task.table[s, 1]
    d = DEPTH_SCALE * (range_m - r0) / task.depth_length_m
    dc = np.clip(d, TARGET_FLOOR, 1.0)
    return Shard(sample_id=task.rows.astype(np.int64), conditions=task.table,
                 nu=task.nu.astype(np.float32),
                 offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
                 pixel=_pixels(lidar, cell_w, cell_h), depth=dc.astype(np.float16),
                 delta_range_m=(range_m - r0).astype(np.float32),
                 clipped=clipped.astype(bool),
                 n_clamped=np.bincount(s, weights=(d != dc), minlength=n).astype(np.int32),
                 n_rays=n_rays.astype(np.int32))


def part_suffix() -> str:
    """Temporary-file suffix unique to this process (concurrent builders share a directory)."""
    return f".{os.getpid()}.part"


def run_task(task: ShardTask) -> tuple[int, int, float]:
    t0 = time.perf_counter()
    wait_point("build.shard-computing")
    shard = compute_shard(task)
    path = Path(task.path)
    write_atomic(path, shard.to_bytes(), part_suffix=part_suffix())
    wait_point("build.shard-written")
    return task.index, len(task.rows), time.perf_counter() - t0
