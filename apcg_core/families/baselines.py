"""The comparison families (the paper's section 3.1: "point-gan", "voxel-gan", "diffusion") at
generation time. A trained comparison model is a directory (model.json + weights.pt +
counts.npz); generation: canonical sets -> observation frame -> snapped to the lidar's cells (one
return per cell, range quantized) -> the condition's expected point count (a random subset of the
cells), so every method's clouds are what the SPC-Lidar records.

The canonical frame: centred on the target's centre of mass and divided by its depth length l,
so every type and range fits [-1, 1]^3. Their networks are :mod:`apcg_core.nn.baselines`
(torch, the only runtime); their training is ``training/families/baselines.py``, whose family
objects (registered by entry point) load these models.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import cached_property

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError, check_int
from ..frames import cartesian_to_spherical, spherical_to_cartesian, target_centres
from .base import GenerationResult, ModelTypes
from .registry import get_family

VOXEL_SURPLUS = 4


@dataclass(frozen=True)
class FamilyConfig:
    family: str  # the registered family's name (apcg_core.families), recorded for model.json
    n_points: int = 256
    voxel_res: int = 32
    diffusion_steps: int = 200

    def __post_init__(self) -> None:
        for name, low in (("n_points", 1), ("diffusion_steps", 1), ("voxel_res", 8)):
            check_int(name, getattr(self, name), low)
        if self.voxel_res & (self.voxel_res - 1):  # 4^3 features doubled k times
            raise InputError(f"voxel_res must be 4 * 2^k (8, 16, 32, 64 ...), got "
                             f"{self.voxel_res}")

    @cached_property
    def schedule(self):
        """The DDPM schedule (``apcg_core.nn.baselines.Schedule``; imports torch)."""
        from ..nn.baselines import Schedule
        return Schedule(self.diffusion_steps)

    def to_dict(self) -> dict:
        return asdict(self)


def to_canonical(xyz: np.ndarray, range_m: float, elevation: float, length_m: float):
    return (xyz - target_centres(range_m, elevation)[0]) / length_m


def from_canonical(pts: np.ndarray, range_m: float, elevation: float, length_m: float):
    return np.asarray(pts, np.float64) * length_m + target_centres(range_m, elevation)[0]


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


class BaselineModel(ModelTypes):
    """A comparison family's model; what differs between the families (networks, sampling)
    is its family object's (``training/families/baselines.py``), found by model.json ``family``."""

    runtime = "torch"
    norm = True
    tau = None
    # Their networks take the type as one scaled number of nu: `apcg teach` cannot add one.
    # (Their output is a point set in the canonical frame, snapped to any lidar's cells: no
    # window size to check against model.json's lidar, as the cGAN's.)
    TEACHABLE = False

    def __init__(self, directory, sampling_steps: int | None = None, family=None) -> None:
        self._read_model_json(directory)
        self.family_impl = family if family is not None else get_family(self.family)
        self.cfg = FamilyConfig(**self.meta["net"])
        import torch
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
        # a whole number >= 0, as the cGAN's: numpy refuses a negative one, and draws
        # unseeded noise from None
        seed = check_int("seed", seed, 0)
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
