"""Training batches from a dataset directory (docs/DATASET.md): normalised depth images + nu.

All shards of a split are held in memory in their sparse form (a few kB per sample); a batch is
made dense and normalised (Norm, eq. 17) on demand, in numpy. The order of batches is a pure
function of (seed, batch counter), so a resumed run sees exactly the batches it would have seen.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from apcg_core.cloud import PointCloud
from apcg_core.condition import scale_ratio
from apcg_core.depth import BACKGROUND, norm
from apcg_core.errors import InputError
from apcg_core.frames import spherical_to_cartesian
from apcg_core.io.dataset import (
    check_complete,
    load_shard,
    read_condition_index,
    read_header,
)
from apcg_core.lidar import LidarParams
from apcg_core.typetable import Conditions, TypeTable


class DepthDataset:
    def __init__(self, directory, split: str = "train") -> None:
        self.directory = Path(directory)
        self.header = read_header(self.directory)
        if split not in ("train", "test"):
            raise InputError(f"split must be 'train' or 'test', got {split!r}")
        # the dataset whole (manifest, every shard there) and each shard the one its header
        # and conditions.csv describe: a shard copied from elsewhere is refused by name
        check_complete(self.directory, self.header)
        index = read_condition_index(self.directory, self.header)
        shards = [load_shard(self.directory, s, index, self.header)
                  for s in self.header["shards"]
                  if s["split"] == split]
        if not shards:
            raise InputError(f"dataset {directory} has no {split} samples")
        self.height = int(self.header["lidar"]["height"])
        self.width = int(self.header["lidar"]["width"])
        self.sample_id = np.concatenate([s.sample_id for s in shards])
        self.conditions = np.concatenate([s.conditions for s in shards])
        self.nu = np.concatenate([s.nu for s in shards]).astype(np.float32)
        counts = np.concatenate([np.diff(s.offsets) for s in shards])
        self.offsets = np.concatenate([[0], np.cumsum(counts)])
        self.pixel = np.concatenate([s.pixel.astype(np.int64) for s in shards])
        self.depth = np.concatenate([s.depth for s in shards]).astype(np.float32)
        self.delta_range_m = np.concatenate([s.delta_range_m for s in shards])
        # each return's cosine of incidence, where the dataset was built with incidence = true
        # (every shard, or the build is refused below: none is half-labelled)
        has = [s.cos_incidence is not None for s in shards]
        if any(has) and not all(has):
            raise InputError(f"dataset {directory}: some shards hold cos_incidence and some "
                             "do not; rebuild it with one config")
        self.cos_incidence = (np.concatenate([s.cos_incidence for s in shards])
                              .astype(np.float32) if all(has) else None)
        self.q = scale_ratio(self.conditions[:, 1])
        self.lidar = LidarParams.from_dict(self.header["lidar"])
        self.types = TypeTable.from_records(self.header["types"], owner=f"dataset {directory}")

    def __len__(self) -> int:
        return len(self.sample_id)

    def condition_rows(self, idx=None) -> Conditions:
        """The conditions of samples ``idx`` (all by default) with the dataset's type table:
        what crosses to a model, which maps them into its own types by name."""
        table = self.conditions if idx is None else self.conditions[np.asarray(idx)]
        return Conditions(self.types, table)

    def is_near(self, idx=None) -> np.ndarray:
        """Whether each sample's type uses the near (drone) range band."""
        codes = self.conditions[:, 0] if idx is None else self.conditions[np.asarray(idx), 0]
        return self.types.is_near(codes.astype(np.int64))

    def images(self, idx: np.ndarray, normalized: bool = True) -> np.ndarray:
        """(B, H, W) float32 depth images of samples ``idx`` (Norm applied if ``normalized``)."""
        idx = np.asarray(idx, dtype=np.int64)
        H, W = self.height, self.width
        out = np.full((len(idx), H * W), BACKGROUND, np.float32)
        starts, stops = self.offsets[idx], self.offsets[idx + 1]
        lens = stops - starts
        rows = np.repeat(np.arange(len(idx)), lens)
        pos = np.repeat(starts - np.concatenate([[0], np.cumsum(lens)[:-1]]), lens) + np.arange(
            lens.sum())
        out[rows, self.pixel[pos]] = self.depth[pos]
        out = out.reshape(len(idx), H, W)
        return norm(out, self.q[idx]) if normalized else out

    def sample_cloud(self, i: int) -> PointCloud:
        """The standard cloud of sample ``i`` with its cells and ranges (observation frame)."""
        lidar = self.lidar
        sl = slice(self.offsets[i], self.offsets[i + 1])
        row, col = np.divmod(self.pixel[sl], self.width)
        w, h = lidar.w_of_col(col), lidar.h_of_row(row)
        a, b = lidar.cell_centre_angles(w, h, self.conditions[i, 2])
        r = self.conditions[i, 1] + self.delta_range_m[sl].astype(np.float64)
        return PointCloud(spherical_to_cartesian(a, b, r), r, w, h)

    def standard_cloud(self, i: int) -> np.ndarray:
        """The standard point cloud (n, 3) of sample ``i`` (observation frame, metres)."""
        return self.sample_cloud(i).xyz

    def batches_per_epoch(self, batch_size: int, world: int = 1) -> int:
        n = len(self) // (batch_size * world)
        if n < 1:
            raise InputError(f"{len(self)} samples are fewer than one batch of {batch_size} "
                             f"x {world} process(es)")
        return n

    def batch_indices(self, seed: int, counter: int, batch_size: int, rank: int = 0,
                      world: int = 1) -> np.ndarray:
        """Samples of the ``counter``-th batch of this rank: a fresh permutation each epoch."""
        bpe = self.batches_per_epoch(batch_size, world)
        epoch, i = divmod(counter, bpe)
        perm = np.random.default_rng([seed, epoch]).permutation(len(self))
        start = (i * world + rank) * batch_size
        return perm[start:start + batch_size]
