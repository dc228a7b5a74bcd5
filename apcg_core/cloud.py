"""A point cloud in the observation frame with its per-point attributes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError

# Per-point photon attributes (SPEC section 8) and their stored types.
PHOTON_FIELDS = {"label": np.uint8, "count": np.int32, "pulse": np.int32}


@dataclass
class PointCloud:
    """Points (N, 3) in the observation frame (metres, float64) and per-point attributes.

    ``range_m`` is the slant range of each point, ``cell_w`` / ``cell_h`` its centred cell,
    ``sample`` the index of the sample a point belongs to when clouds of a batch are stacked.
    A photon cloud (SPEC section 8) also carries ``label`` (1 signal, 0 noise), ``count`` (the
    events in the point's bin) and, as events, ``pulse``; an ideal cloud has none of them.
    """

    xyz: np.ndarray
    range_m: np.ndarray
    cell_w: np.ndarray
    cell_h: np.ndarray
    sample: np.ndarray | None = None
    label: np.ndarray | None = None
    count: np.ndarray | None = None
    pulse: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        n = len(self.xyz)
        self.range_m = np.asarray(self.range_m, dtype=np.float64).reshape(-1)
        self.cell_w = np.asarray(self.cell_w, dtype=np.int32).reshape(-1)
        self.cell_h = np.asarray(self.cell_h, dtype=np.int32).reshape(-1)
        if self.sample is not None:
            self.sample = np.asarray(self.sample, dtype=np.int64).reshape(-1)
        for name, dtype in PHOTON_FIELDS.items():
            if getattr(self, name) is not None:
                setattr(self, name, np.asarray(getattr(self, name), dtype=dtype).reshape(-1))
        for name in ("range_m", "cell_w", "cell_h", "sample", *PHOTON_FIELDS):
            a = getattr(self, name)
            if a is not None and len(a) != n:
                raise InputError(f"PointCloud.{name} has {len(a)} values for {n} points")

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def empty(self) -> bool:
        return len(self.xyz) == 0

    @property
    def photon_fields(self) -> list[str]:
        """The photon attributes this cloud carries (none for an ideal cloud)."""
        return [f for f in PHOTON_FIELDS if getattr(self, f) is not None]

    def select(self, mask) -> PointCloud:
        def pick(a):
            return None if a is None else a[mask]
        return PointCloud(self.xyz[mask], self.range_m[mask], self.cell_w[mask],
                          self.cell_h[mask], pick(self.sample),
                          *(pick(getattr(self, f)) for f in PHOTON_FIELDS))

    def split(self, n_samples: int) -> list[PointCloud]:
        """One cloud per sample of a batch (points keep their order)."""
        if self.sample is None:
            raise InputError("this cloud has no sample index; it is not a batch")
        order = np.argsort(self.sample, kind="stable")
        bounds = np.searchsorted(self.sample[order], np.arange(n_samples + 1))
        return [self.select(order[bounds[i]:bounds[i + 1]]) for i in range(n_samples)]
