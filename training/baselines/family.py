"""A comparison family's networks and their configuration, as the trainer and the model use
them."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import cached_property

from apcg_core.errors import InputError, check_int

from . import FAMILIES
from .data import CanonicalClouds  # noqa: F401 - the trainer takes it from here
from .nets import Denoiser, PointCritic, PointGenerator, Schedule, VoxelCritic, VoxelGenerator


@dataclass(frozen=True)
class FamilyConfig:
    family: str
    n_points: int = 256
    voxel_res: int = 32
    diffusion_steps: int = 200

    def __post_init__(self) -> None:
        if self.family not in FAMILIES[1:]:
            raise InputError(f"unknown model family {self.family!r}; accepted: "
                             f"{', '.join(FAMILIES)}")
        for name, low in (("n_points", 1), ("diffusion_steps", 1), ("voxel_res", 8)):
            check_int(name, getattr(self, name), low)
        if self.voxel_res & (self.voxel_res - 1):  # 4^3 features doubled k times
            raise InputError(f"voxel_res must be 4 * 2^k (8, 16, 32, 64 ...), got "
                             f"{self.voxel_res}")

    @cached_property
    def schedule(self) -> Schedule:
        return Schedule(self.diffusion_steps)

    def networks(self):
        """(generator or denoiser, critic or None)."""
        if self.family == "point-gan":
            return PointGenerator(self.n_points), PointCritic()
        if self.family == "voxel-gan":
            return VoxelGenerator(self.voxel_res), VoxelCritic(self.voxel_res)
        return Denoiser(), None

    def to_dict(self) -> dict:
        return asdict(self)


def build_family(cfg) -> FamilyConfig:
    return FamilyConfig(cfg.family, cfg.n_points, cfg.voxel_res, cfg.diffusion_steps)
