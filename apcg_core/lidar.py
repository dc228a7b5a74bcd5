"""SPC-Lidar parameters (SPEC section 1), the geometry of its depth-image window, and the one
lidar description every command takes (``--lidar PRESET|FILE``): a TOML file whose ``[lidar]``
table is the one the dataset configs hold, plus an optional ``[sensor]`` table (SPEC section 8,
read by ``apcg_core.sensor``). Presets are the files beside this module in ``lidar_presets/``;
``paper`` is the default.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError, check_finite
from .io.toml_file import read_toml

DEG = math.pi / 180.0
LIDAR_PRESET_DIR = Path(__file__).with_name("lidar_presets")
DEFAULT_LIDAR_PRESET = "paper"  # the paper's SPC-Lidar (SPEC section 1; its file cites it)
LIDAR_KEYS = ("r_alpha_deg", "r_beta_deg", "r_r_m", "width", "height")
MAX_WINDOW_SIDE = 65536  # cells a side a lidar file may ask for (a window's cells index int32)
# The tables a lidar file may hold: [lidar] (here) and [sensor] (apcg_core.sensor.params).
LIDAR_FILE_TABLES = ("lidar", "sensor")


# What a lidar's cells and bins may be: wide enough for every single-photon lidar we know of,
# narrow enough that the arithmetic stays finite and a window's arrays fit in memory. A 1 um
# bin is 6.7 fs of flight time, far below any timing electronics (SPAD TCSPC jitter is tens
# of ps: Hadfield, Nature Photonics 3, 696 (2009)); a 1 km bin is beyond any range gate's use.
# A 1e-7 deg cell is 0.03 mm at 18 km; one of 10 deg gives 18 cells across a 180 deg window.
_BOUNDS = {  # name: (lowest, highest, unit shown, factor to the unit shown, what it is)
    "r_alpha": (1e-7 * DEG, 10.0 * DEG, "_deg", DEG,
                "an azimuth cell from 1e-7 deg (0.03 mm at 18 km) to 10 deg"),
    "r_beta": (1e-7 * DEG, 10.0 * DEG, "_deg", DEG,
               "an elevation cell from 1e-7 deg (0.03 mm at 18 km) to 10 deg"),
    "r_r": (1e-6, 1e3, "_m", 1.0, "a range bin from 1 um (6.7 fs of flight) to 1 km"),
}


def _number(name: str, value) -> float:
    """``value`` as a finite float; a text is refused, not read (float("64") would take it)."""
    if isinstance(value, (str, bytes)):
        raise InputError(f"{name} must be a number, got {value!r}")
    return check_finite(name, value)


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
        # the values checked are the values kept: a text "0.0001" is checked as a number and
        # then kept as the number, never as the text (which the window check would multiply)
        for name, (lo, hi, unit, scale, what) in self._bounds().items():
            v = _number(name, getattr(self, name))
            if not lo <= v <= hi:
                raise InputError(
                    f"{name}{unit} = {v / scale!r} is outside [{lo / scale!r}, {hi / scale!r}]"
                    f"{'' if v > 0 else ' (it must be > 0)'}: {what}")
            object.__setattr__(self, name, v)
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 2 or v % 2:
                raise InputError(f"{name} must be an even integer >= 2, got {v!r}")
            object.__setattr__(self, name, int(v))
        if self.width * self.r_alpha >= math.pi or self.height * self.r_beta >= math.pi / 2:
            raise InputError(
                f"the window must span less than 180 deg azimuth and 90 deg elevation, got "
                f"width x r_alpha_deg = {self.width} x {self.r_alpha / DEG:g} = "
                f"{self.width * self.r_alpha / DEG:g} deg, height x r_beta_deg = "
                f"{self.height} x {self.r_beta / DEG:g} = {self.height * self.r_beta / DEG:g} "
                "deg")

    @classmethod
    def _bounds(cls) -> dict:
        return _BOUNDS

    @classmethod
    def from_degrees(cls, r_alpha_deg: float = 0.0040, r_beta_deg: float = 0.0076,
                     r_r_m: float = 0.15, width: int = 256, height: int = 64) -> LidarParams:
        # width and height as given: int() would truncate 256.9 to 256 (and name 3.7 as 3)
        return cls(_number("r_alpha_deg", r_alpha_deg) * DEG,
                   _number("r_beta_deg", r_beta_deg) * DEG, r_r_m, width, height)

    def to_dict(self) -> dict:
        """Edge representation (degrees, metres), as stored in configs and dataset headers."""
        return {"r_alpha_deg": self.r_alpha / DEG, "r_beta_deg": self.r_beta / DEG,
                "r_r_m": self.r_r, "width": self.width, "height": self.height}

    @classmethod
    def from_dict(cls, d: dict) -> LidarParams:
        return lidar_from_table(d)

    def describe(self) -> str:
        """One line: cells, bins, window (for messages)."""
        d = self.to_dict()
        return (f"{d['r_alpha_deg']:.6g} x {d['r_beta_deg']:.6g} deg cells, {self.r_r:g} m bins, "
                f"{self.width} x {self.height} window")

    def window_that_fits(self, alpha_lo, alpha_hi, beta_lo, beta_hi, beta0) -> tuple[int, int]:
        """The smallest even W x H window (at these cells) holding every cell that the angular
        extents [alpha_lo, alpha_hi] x [beta_lo, beta_hi] (rad, arrays: one per target) touch,
        the window centred as in SPEC section 5 (w in [-W/2, W/2 - 1])."""
        w_lo, h_lo = self.cell_of_angles(alpha_lo, beta_lo, beta0)
        w_hi, h_hi = self.cell_of_angles(alpha_hi, beta_hi, beta0)
        half_w = int(max(np.max(-np.asarray(w_lo)), np.max(np.asarray(w_hi)) + 1, 1))
        half_h = int(max(np.max(-np.asarray(h_lo)), np.max(np.asarray(h_hi)) + 1, 1))
        return 2 * half_w, 2 * half_h

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

    def clip_box(self, w_half, h_half):
        """The cells w in [-w_half, w_half] x h in [-h_half, h_half] about the window's centre,
        cut to the window: (w_lo, w_hi, h_lo, h_hi), inclusive."""
        return (np.maximum(-np.asarray(w_half), self.w_min),
                np.minimum(w_half, self.width // 2 - 1),
                np.maximum(-np.asarray(h_half), self.h_min),
                np.minimum(h_half, self.height // 2 - 1))

    def cell_centre_angles(self, w, h, beta0: float):
        """Azimuth and elevation of the centres of cells (w, h) (paper eqs. 3-4)."""
        return (np.asarray(w, dtype=np.float64) * self.r_alpha,
                np.asarray(h, dtype=np.float64) * self.r_beta + beta0)

    def quantize_range(self, r):
        """Range quantized to the centre of its time bin: (floor(r / R_r) + 0.5) R_r."""
        return (np.floor(np.asarray(r, dtype=np.float64) / self.r_r) + 0.5) * self.r_r


# A derived lidar's cells may be this many times finer than a lidar's finest (a 1e-7 deg
# lidar's 3 x 3 sub-rays, sensor/generated.py): its arithmetic is float64 cell indices times
# cell sizes, finite and exact enough at 6e-9 deg (2 um at 18 km).
MAX_FINER = 16
_FINER_BOUNDS = {name: ((lo / MAX_FINER, *rest) if name in ("r_alpha", "r_beta") else
                        (lo, *rest)) for name, (lo, *rest) in _BOUNDS.items()}


@dataclass(frozen=True)
class FinerLidar(LidarParams):
    """A lidar the package derives from a user's (the K-times finer lidar whose cells are a
    generated cloud's sub-rays): its cells may be up to :data:`MAX_FINER` times finer than
    the finest a lidar may have; every other limit (bins, an even window under 180 x 90 deg)
    is any lidar's. Never read from a user's file or option."""

    @classmethod
    def _bounds(cls) -> dict:
        return _FINER_BOUNDS


# --- the lidar description: presets, files and tables ----------------------------------------
def lidar_preset_names() -> list[str]:
    return sorted(p.stem for p in LIDAR_PRESET_DIR.glob("*.toml"))


def _where(source: str) -> str:
    return f" in {source}" if source else ""


def lidar_from_table(table, source: str = "") -> LidarParams:
    """A ``[lidar]`` table (a lidar file's, a dataset config's, a model's or a dataset's record)
    as :class:`LidarParams`, every value checked by name. A key left out takes the paper's
    value (SPEC section 1), as the dataset configs always have."""
    if not isinstance(table, dict):
        raise InputError(f"the [lidar] table{_where(source)} must be a table of keys "
                         f"({', '.join(LIDAR_KEYS)}), got {table!r}")
    unknown = sorted(set(table) - set(LIDAR_KEYS))
    if unknown:
        raise InputError(f"unknown lidar key(s) {', '.join(map(repr, unknown))}"
                         f"{_where(source)}; accepted: {', '.join(LIDAR_KEYS)}")
    values = {}
    for key in LIDAR_KEYS[:3]:
        if key in table:
            v = table[key]
            ok = (isinstance(v, (int, float)) and not isinstance(v, bool)
                  and math.isfinite(v) and v > 0)
            if not ok:
                raise InputError(f"lidar value {key}{_where(source)} must be a finite number "
                                 f"> 0, got {v!r}")
            values[key] = float(v)
    for key in LIDAR_KEYS[3:]:
        if key in table:
            v = table[key]
            if (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not
                    2 <= v <= MAX_WINDOW_SIDE or v % 2):
                raise InputError(f"lidar value {key}{_where(source)} must be an even integer "
                                 f"from 2 to {MAX_WINDOW_SIDE}, got {v!r}")
            values[key] = int(v)
    try:
        return LidarParams.from_degrees(**values)
    except InputError as exc:
        raise InputError(f"{exc}{_where(source)}") from None


def lidar_file(ref) -> Path:
    """The file of a lidar preset name or a lidar file path; a named error otherwise."""
    from .typetable import find_preset  # the one preset lookup (names in any spelling)
    preset = find_preset(ref, LIDAR_PRESET_DIR)
    if preset is not None:
        return preset
    ref_s = str(ref).strip()
    path = Path(ref_s).expanduser()
    if ref_s and path.is_dir():
        raise InputError(f"lidar {ref_s!r} is a directory; give a preset or a TOML file with "
                         "a [lidar] table")
    if not ref_s or not path.is_file():
        raise InputError(f"unknown lidar {ref_s!r}: not a preset and no such file; presets: "
                         f"{', '.join(lidar_preset_names())}, or a TOML file with a [lidar] "
                         "table")
    return path


def read_lidar_file(ref) -> tuple[Path, dict]:
    """The path and parsed tables of a lidar preset or file, its tables checked by name."""
    path = lidar_file(ref)
    doc = read_toml(path)
    unknown = sorted(set(doc) - set(LIDAR_FILE_TABLES))
    if unknown:
        raise InputError(f"{path}: unknown table(s) or key(s) {', '.join(map(repr, unknown))}; "
                         f"a lidar file holds a [lidar] table and optionally a [sensor] table")
    if "lidar" not in doc:
        raise InputError(f"{path} has no [lidar] table (keys {', '.join(LIDAR_KEYS)}); see the "
                         f"presets in {LIDAR_PRESET_DIR}")
    return path, doc


def load_lidar(ref=None) -> LidarParams:
    """The lidar of a preset name or a lidar file (its ``[lidar]`` table); None: the default
    preset, ``paper``."""
    path, doc = read_lidar_file(DEFAULT_LIDAR_PRESET if ref is None else ref)
    return lidar_from_table(doc["lidar"], source=str(path))


def lidar_sensor_file(ref) -> Path | None:
    """The lidar file itself when it also holds a ``[sensor]`` table (the sensor module reads
    that table from it), else None."""
    if ref is None:
        return None
    path, doc = read_lidar_file(ref)
    return path if "sensor" in doc else None


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'


def lidar_file_text(lidar: LidarParams, sensor: dict | None = None, comment: str = "") -> str:
    """A lidar file: the ``[lidar]`` table of ``lidar`` (degrees, metres, rounded to what a
    person types) and, when given, a ``[sensor]`` table (``SensorParams.to_dict()``);
    :func:`load_lidar` reads it back to the same lidar."""
    d = lidar.to_dict()
    d = {k: (round(v, 10) if isinstance(v, float) else v) for k, v in d.items()}
    lines = [f"# {ln}" for ln in comment.splitlines()] + ["[lidar]"]
    lines += [f"{k} = {_toml_value(d[k])}" for k in LIDAR_KEYS]
    if sensor:
        lines += ["", "[sensor]"] + [f"{k} = {_toml_value(v)}" for k, v in sensor.items()]
    return "\n".join(lines) + "\n"
