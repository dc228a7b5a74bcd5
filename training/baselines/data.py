"""Standard clouds in a canonical frame for the point and voxel models: centred on the target's
centre of mass and divided by its depth length l, so every type and range fits [-1, 1]^3; and the
expected point count of a condition (the nearest training conditions of the same type)."""

from __future__ import annotations

import numpy as np

from apcg_core.frames import target_centres

from ..data import DepthDataset


def to_canonical(xyz: np.ndarray, range_m: float, elevation: float, length_m: float):
    return (xyz - target_centres(range_m, elevation)[0]) / length_m


def from_canonical(pts: np.ndarray, range_m: float, elevation: float, length_m: float):
    return np.asarray(pts, np.float64) * length_m + target_centres(range_m, elevation)[0]


class CanonicalClouds:
    """The train split's clouds in the canonical frame (kept in memory, a few MB)."""

    def __init__(self, ds: DepthDataset) -> None:
        self.ds = ds
        lengths = ds.types.column("depth_length_m").astype(np.float64)
        self.length = lengths[ds.conditions[:, 0].astype(int)]
        self.counts = np.diff(ds.offsets)
        self.clouds = [to_canonical(ds.standard_cloud(i), ds.conditions[i, 1],
                                    ds.conditions[i, 2], self.length[i]).astype(np.float32)
                       for i in range(len(ds))]

    def points(self, idx, n: int, seed: int) -> np.ndarray:
        """(B, n, 3): each cloud resampled to n points (with replacement when it has fewer;
        an empty cloud gives n copies of the centre)."""
        rng = np.random.default_rng(seed)
        out = np.zeros((len(idx), n, 3), np.float32)
        for k, i in enumerate(idx):
            c = self.clouds[int(i)]
            if len(c):
                out[k] = c[rng.choice(len(c), n, replace=len(c) < n)]
        return out

    def voxels(self, idx, res: int) -> np.ndarray:
        """(B, 1, res, res, res) occupancy of each cloud over [-1, 1]^3."""
        out = np.zeros((len(idx), 1, res, res, res), np.float32)
        for k, i in enumerate(idx):
            v = voxel_index(self.clouds[int(i)], res)
            out[k, 0, v[:, 0], v[:, 1], v[:, 2]] = 1.0
        return out


def voxel_index(pts: np.ndarray, res: int) -> np.ndarray:
    return np.clip(((np.asarray(pts) + 1.0) / 2.0 * res).astype(np.int64), 0, res - 1)


def voxel_centres(res: int) -> np.ndarray:
    """(res^3, 3) canonical coordinates of every voxel centre, in C order."""
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    return np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)


class CountLookup:
    """Expected points for a condition: the mean count of the k training samples of the same
    type nearest in nu (L1)."""

    def __init__(self, codes: np.ndarray, nu: np.ndarray, counts: np.ndarray, k: int = 5):
        self.codes, self.nu, self.counts, self.k = codes.astype(int), nu, counts, k

    def __call__(self, code: int, nu: np.ndarray) -> int:
        same = np.flatnonzero(self.codes == int(code))
        if len(same) == 0:
            return int(np.median(self.counts))
        d = np.abs(self.nu[same, 1:] - nu[1:]).sum(axis=1)
        near = same[np.argsort(d)[: self.k]]
        return int(round(float(self.counts[near].mean())))

    def to_dict(self) -> dict:
        return {"codes": self.codes.tolist(), "nu": np.round(self.nu, 5).tolist(),
                "counts": self.counts.astype(int).tolist(), "k": self.k}

    @classmethod
    def from_dict(cls, d: dict) -> CountLookup:
        return cls(np.array(d["codes"]), np.array(d["nu"], np.float32), np.array(d["counts"]),
                   d["k"])
