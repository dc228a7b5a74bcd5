"""SPC-Lidar parameters (SPEC section 1) and the geometry of its depth-image window."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError, check_finite

DEG = math.pi / 180.0


@dataclass(frozen=True)
class LidarParams:
    """Angular and range resolution of the lidar and the size of the depth-image window.

    All angles in radians, ranges in metres. Use :meth:`from_degrees` at the edges.
    Defaults are the paper's: 0.0040 deg x 0.0076 deg cells, 0.15 m range bins, 256 x 64 pixels.
    """

    r_alpha: float = 0.0040 * DEG  # azimuth resolution (rad)
    r_beta: float = 0.0076 * DEG  # elevation resolution (rad)
    r_r: float = 0.15  # range resolution, the time-bin width (m)
    width: int = 256  # azimuth cells W
    height: int = 64  # elevation cells H

    def __post_init__(self) -> None:
        for name in ("r_alpha", "r_beta", "r_r"):
            v = check_finite(name, getattr(self, name))
            if v <= 0:
                raise InputError(f"{name} must be > 0, got {v!r}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < 2 or v % 2:
                raise InputError(f"{name} must be an even integer >= 2, got {v!r}")
        if self.width * self.r_alpha >= math.pi or self.height * self.r_beta >= math.pi / 2:
            raise InputError("the window must span less than 180 deg azimuth and 90 deg elevation")

    @classmethod
    def from_degrees(cls, r_alpha_deg: float = 0.0040, r_beta_deg: float = 0.0076,
                     r_r_m: float = 0.15, width: int = 256, height: int = 64) -> LidarParams:
        return cls(r_alpha_deg * DEG, r_beta_deg * DEG, r_r_m, int(width), int(height))

    def to_dict(self) -> dict:
        """Edge representation (degrees, metres), as stored in configs and dataset headers."""
        return {"r_alpha_deg": self.r_alpha / DEG, "r_beta_deg": self.r_beta / DEG,
                "r_r_m": self.r_r, "width": self.width, "height": self.height}

    @classmethod
    def from_dict(cls, d: dict) -> LidarParams:
        return cls.from_degrees(**d)

    # --- pixel <-> centred cell coordinates (SPEC section 5) -------------------------------
    @property
    def w_min(self) -> int:
        return -self.width // 2

    @property
    def h_min(self) -> int:
        return -self.height // 2

    def w_of_col(self, col):
        """Centred azimuth index w of array column ``col`` (column 0 is w = -W/2)."""
        return np.asarray(col) - self.width // 2

    def h_of_row(self, row):
        """Centred elevation index h of array row ``row`` (row 0 is the top, h = H/2 - 1)."""
        return self.height // 2 - 1 - np.asarray(row)

    def col_of_w(self, w):
        return np.asarray(w) + self.width // 2

    def row_of_h(self, h):
        return self.height // 2 - 1 - np.asarray(h)

    def cell_of_angles(self, alpha, beta, beta0: float):
        """Nearest cell (w, h) of directions (alpha, beta): cell w covers [(w-.5)Ra, (w+.5)Ra]."""
        w = np.floor(np.asarray(alpha, dtype=np.float64) / self.r_alpha + 0.5).astype(np.int64)
        h = np.floor((np.asarray(beta, dtype=np.float64) - beta0) / self.r_beta + 0.5)
        return w, h.astype(np.int64)

    def inside(self, w, h):
        """True where centred cell (w, h) lies inside the W x H window."""
        w = np.asarray(w)
        h = np.asarray(h)
        return ((w >= -self.width // 2) & (w < self.width // 2)
                & (h >= -self.height // 2) & (h < self.height // 2))

    def cell_centre_angles(self, w, h, beta0: float):
        """Azimuth and elevation of the centres of cells (w, h) (paper eqs. 3-4)."""
        return (np.asarray(w, dtype=np.float64) * self.r_alpha,
                np.asarray(h, dtype=np.float64) * self.r_beta + beta0)

    def quantize_range(self, r):
        """Range quantized to the centre of its time bin: (floor(r / R_r) + 0.5) R_r."""
        return (np.floor(np.asarray(r, dtype=np.float64) / self.r_r) + 0.5) * self.r_r
