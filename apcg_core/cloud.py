"""A point cloud in the observation frame with its per-point attributes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError


@dataclass
class PointCloud:
    """Points (N, 3) in the observation frame (metres, float64) and per-point attributes.

    ``range_m`` is the slant range of each point, ``cell_w`` / ``cell_h`` its centred cell,
    ``sample`` the index of the sample a point belongs to when clouds of a batch are stacked.
    """

    xyz: np.ndarray
    range_m: np.ndarray
    cell_w: np.ndarray
    cell_h: np.ndarray
    sample: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        n = len(self.xyz)
        self.range_m = np.asarray(self.range_m, dtype=np.float64).reshape(-1)
        self.cell_w = np.asarray(self.cell_w, dtype=np.int32).reshape(-1)
        self.cell_h = np.asarray(self.cell_h, dtype=np.int32).reshape(-1)
        if self.sample is not None:
            self.sample = np.asarray(self.sample, dtype=np.int64).reshape(-1)
        for name in ("range_m", "cell_w", "cell_h", "sample"):
            a = getattr(self, name)
            if a is not None and len(a) != n:
                raise InputError(f"PointCloud.{name} has {len(a)} values for {n} points")

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def empty(self) -> bool:
        return len(self.xyz) == 0

    def select(self, mask) -> PointCloud:
        return PointCloud(self.xyz[mask], self.range_m[mask], self.cell_w[mask],
                          self.cell_h[mask], None if self.sample is None else self.sample[mask])

    def split(self, n_samples: int) -> list[PointCloud]:
        """One cloud per sample of a batch (points keep their order)."""
        if self.sample is None:
            raise InputError("this cloud has no sample index; it is not a batch")
        order = np.argsort(self.sample, kind="stable")
        bounds = np.searchsorted(self.sample[order], np.arange(n_samples + 1))
        return [self.select(order[bounds[i]:bounds[i + 1]]) for i in range(n_samples)]
