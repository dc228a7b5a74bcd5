"""A comparison family's network configuration, as the trainer saves it with every checkpoint
and the model reads it back from model.json ``net``. What the family builds from it (networks,
batches, sampling) is its family object's, in ``training/families.py``."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import cached_property

from apcg_core.errors import InputError, check_int


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
        """The DDPM schedule (``training.baselines.nets.Schedule``; imports torch)."""
        from .nets import Schedule
        return Schedule(self.diffusion_steps)

    def to_dict(self) -> dict:
        return asdict(self)
