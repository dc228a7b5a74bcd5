"""How one frame of a scene is fired (issue 36): the ``[scan]`` table's pattern.

A pattern divides the lidar's W x H window into groups of cells fired together and gives
each group its firing time after the frame's start. A target is drawn in each group where it
was at that group's time, so a target that moves while the window is scanned comes out
skewed (motion distortion), as a scanning lidar records it. Patterns register themselves in
``PATTERNS`` with the keys they take.

Cells are centred indices (SPEC section 5): w from -W/2 (left) to W/2 - 1, h from -H/2
(bottom) to H/2 - 1 (top). numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..lidar import LidarParams


@dataclass(frozen=True)
class Groups:
    """Cells fired together: group g holds w in [w_lo[g], w_hi[g]] x h in [h_lo[g], h_hi[g]]
    and fires ``time_s[g]`` after the frame's start."""

    time_s: np.ndarray
    w_lo: np.ndarray
    w_hi: np.ndarray
    h_lo: np.ndarray
    h_hi: np.ndarray

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def duration_s(self) -> float:
        return float(self.time_s.max()) if len(self) else 0.0


PATTERNS: dict = {}  # name -> (class, keys: name -> what is accepted)


def register(name: str, keys: dict):
    def deco(cls):
        PATTERNS[name] = (cls, keys)
        cls.name = name
        return cls
    return deco


@register("flash", {})
class Flash:
    """Every cell at once (a flash lidar; and `apcg scene scan`'s default): one group."""

    def groups(self, lidar: LidarParams) -> Groups:
        W2, H2 = lidar.width // 2, lidar.height // 2
        one = np.ones(1, np.int64)
        return Groups(np.zeros(1), -W2 * one, (W2 - 1) * one, -H2 * one, (H2 - 1) * one)

    def to_dict(self) -> dict:
        return {"pattern": self.name}


_LINE = "the time between two lines in seconds, > 0"


@register("rows", {"line_time_s": _LINE,
                   "order": '"top-down" (default: the top row first) or "bottom-up"'})
class Rows:
    """One row of the window after another, ``line_time_s`` apart: every cell of a row fires
    at once (a line-scanning lidar); top row first unless ``order = "bottom-up"``."""

    def __init__(self, line_time_s, order="top-down") -> None:
        if order not in ("top-down", "bottom-up"):
            raise InputError(f'[scan] order = {order!r} is not accepted: "top-down" or '
                             '"bottom-up"')
        self.line_time_s, self.order = float(line_time_s), order

    def groups(self, lidar: LidarParams) -> Groups:
        W2, H2 = lidar.width // 2, lidar.height // 2
        h = np.arange(-H2, H2)
        k = (H2 - 1 - h) if self.order == "top-down" else (h + H2)
        ones = np.ones(len(h), np.int64)
        return Groups(k * self.line_time_s, -W2 * ones, (W2 - 1) * ones, h, h)

    def to_dict(self) -> dict:
        return {"pattern": self.name, "line_time_s": self.line_time_s, "order": self.order}


@register("columns", {"line_time_s": _LINE,
                      "order": '"left-right" (default: the left column first) or "right-left"'})
class Columns:
    """One column of the window after another, ``line_time_s`` apart (a scanner sweeping in
    azimuth with a vertical line of detectors); left column first unless
    ``order = "right-left"``."""

    def __init__(self, line_time_s, order="left-right") -> None:
        if order not in ("left-right", "right-left"):
            raise InputError(f'[scan] order = {order!r} is not accepted: "left-right" or '
                             '"right-left"')
        self.line_time_s, self.order = float(line_time_s), order

    def groups(self, lidar: LidarParams) -> Groups:
        W2, H2 = lidar.width // 2, lidar.height // 2
        w = np.arange(-W2, W2)
        k = (w + W2) if self.order == "left-right" else (W2 - 1 - w)
        ones = np.ones(len(w), np.int64)
        return Groups(k * self.line_time_s, w, w, -H2 * ones, (H2 - 1) * ones)

    def to_dict(self) -> dict:
        return {"pattern": self.name, "line_time_s": self.line_time_s, "order": self.order}


_CELL = "the time between two cells in seconds, > 0"


@register("cells", {"cell_time_s": _CELL,
                    "order": '"rows" (default: along each row, left to right, the top row '
                             'first) or "columns" (down each column, the left column first)'})
class Cells:
    """One cell after another, ``cell_time_s`` apart (a single-beam raster scanner): along
    each row from the left, the top row first; ``order = "columns"`` goes down each column
    from the top, the left column first. Every cell is a group of its own."""

    def __init__(self, cell_time_s, order="rows") -> None:
        if order not in ("rows", "columns"):
            raise InputError(f'[scan] order = {order!r} is not accepted: "rows" or "columns"')
        self.cell_time_s, self.order = float(cell_time_s), order

    def groups(self, lidar: LidarParams) -> Groups:
        W2, H2 = lidar.width // 2, lidar.height // 2
        h, w = np.meshgrid(np.arange(H2 - 1, -H2 - 1, -1), np.arange(-W2, W2), indexing="ij")
        w, h = w.ravel(), h.ravel()  # row by row from the top, left to right in a row
        row, col = H2 - 1 - h, w + W2
        k = (row * lidar.width + col if self.order == "rows"
             else col * lidar.height + row)
        return Groups(k * self.cell_time_s, w, w, h, h)

    def to_dict(self) -> dict:
        return {"pattern": self.name, "cell_time_s": self.cell_time_s, "order": self.order}


_TIME_KEYS = {"line_time_s": _LINE, "cell_time_s": _CELL}


def make_pattern(table: dict | None, source: str):
    """The scan pattern of a ``[scan]`` table (None: flash)."""
    if table is None:
        return Flash()
    if not isinstance(table, dict):
        raise InputError(f"{source}: [scan] must be a table with a pattern "
                         f"({', '.join(PATTERNS)}), got {table!r}")
    name = table.get("pattern")
    if name not in PATTERNS:
        raise InputError(f"{source}: [scan] pattern = {name!r} is unknown; accepted: "
                         f"{', '.join(PATTERNS)}")
    cls, keys = PATTERNS[name]
    args = {k: v for k, v in table.items() if k != "pattern"}
    unknown = sorted(set(args) - set(keys))
    if unknown:
        raise InputError(f"{source}: unknown key(s) {', '.join(unknown)} in [scan] for pattern "
                         f"{name}; accepted: {', '.join(keys) or 'none'}")
    for key in sorted(set(keys) & set(_TIME_KEYS)):  # every pattern's time step, one rule
        v = args.get(key)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) \
                or v <= 0:
            raise InputError(f"{source}: [scan] {key} = {v!r} is not accepted: "
                             f"{_TIME_KEYS[key]}")
    try:
        return cls(**args)
    except InputError as exc:
        raise InputError(f"{source}: {exc}") from None
