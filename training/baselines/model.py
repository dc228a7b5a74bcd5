"""A trained comparison model as a directory (model.json + weights.pt + counts.npz) and its
generation: canonical sets -> observation frame -> snapped to the lidar's cells (one return per
cell, range quantized) -> the condition's expected point count (a random subset of the cells), so
every method's clouds are what the SPC-Lidar records."""

from __future__ import annotations

import numpy as np
import torch

from apcg_core.cloud import PointCloud
from apcg_core.families import get_family
from apcg_core.frames import cartesian_to_spherical, spherical_to_cartesian
from apcg_core.generation import GenerationResult, ModelTypes

from .data import CountLookup, from_canonical
from .family import FamilyConfig

VOXEL_SURPLUS = 4


class BaselineModel(ModelTypes):
    """A comparison family's model; what differs between the families (networks, sampling)
    is its family object's (``training/families.py``), found by model.json ``family``."""

    runtime = "torch"
    norm = True
    tau = None

    def __init__(self, directory, sampling_steps: int | None = None, family=None) -> None:
        self._read_model_json(directory)
        self.family_impl = family if family is not None else get_family(self.family)
        self.cfg = FamilyConfig(**self.meta["net"])
        st = torch.load(self.directory / "weights.pt", map_location="cpu", weights_only=False)
        self.net, _ = self.family_impl.networks(self.cfg)
        self.net.load_state_dict(st["G"])
        self.net.eval()
        with np.load(self.directory / "counts.npz") as z:
            self.counts = CountLookup(z["codes"], z["nu"], z["counts"], int(z["k"]))
        self.sampling_steps = self.family_impl.model_sampling_steps(self.meta, sampling_steps,
                                                                    self.cfg)

    def canonical(self, nu: np.ndarray, seed: int, counts) -> list[np.ndarray]:
        """Point sets (n, 3) in the canonical frame for conditions ``nu``; ``counts[i]`` is
        how many points sample ``i`` may use (a voxel grid keeps its most probable ones)."""
        return self.family_impl.canonical(self, nu, seed, counts)

    def generate(self, conditions, count: int = 1, seed: int = 0) -> GenerationResult:
        table = self.repeated_conditions(conditions, count)
        nu = self.space.encode(table)
        counts = [self.counts(int(table[i, 0]), nu[i]) for i in range(len(table))]
        # voxels behind one another fall into one cell: offer more than the count asks for
        sets = self.canonical(nu, seed, [VOXEL_SURPLUS * n for n in counts])
        lengths = self.depth_length(table[:, 0])
        rng = np.random.default_rng(seed)
        parts = []
        for i, (pts, n) in enumerate(zip(sets, counts, strict=True)):
            if not np.isfinite(pts).all():  # never drop such points silently (they have no cell)
                raise RuntimeError(f"the {self.family} network produced "
                                   f"{int((~np.isfinite(pts)).any(-1).sum())} non-finite points "
                                   f"for condition {table[i].tolist()} (sample {i})")
            xyz = from_canonical(pts, table[i, 1], table[i, 2], lengths[i])
            cells = self._snap(xyz, table[i, 2], i)
            if len(cells[0]) > n:  # the expected count for the condition, after snapping
                keep = np.sort(rng.permutation(len(cells[0]))[:n])
                cells = tuple(c[keep] for c in cells)
            parts.append(cells)
        cloud = PointCloud(*[np.concatenate([p[k] for p in parts]) for k in range(5)])
        return self.result(cloud, None, table)

    def _snap(self, xyz: np.ndarray, beta0: float, sample: int):
        """Points -> the lidar's cells: the nearest point of each cell, its range quantized."""
        lidar = self.lidar
        alpha, beta, r = cartesian_to_spherical(xyz)
        w, h = lidar.cell_of_angles(alpha, beta, beta0)
        ok = lidar.inside(w, h)
        w, h, r = w[ok], h[ok], r[ok]
        order = np.lexsort((r, h, w))
        w, h, r = w[order], h[order], r[order]
        first = np.ones(len(w), bool)
        first[1:] = (w[1:] != w[:-1]) | (h[1:] != h[:-1])
        w, h, r = w[first], h[first], lidar.quantize_range(r[first])
        a, b = lidar.cell_centre_angles(w, h, beta0)
        return (spherical_to_cartesian(a, b, r), r, w, h,
                np.full(len(r), sample, np.int64))
