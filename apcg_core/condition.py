"""A sample's condition (type, range, elevation, attitude) and its vector nu (SPEC section 3).

Inside the code angles are radians and ranges metres; ``Condition.from_degrees`` and
``ConditionSpace.to_dict`` are the edges where degrees appear.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from numbers import Integral

import numpy as np

from .errors import InputError, check_finite, check_int, check_range, distinct
from .frames import ATTITUDE
from .lidar import DEG
from .typetable import each_once

# Column order of a condition table and of nu. The type column holds a code of the type table
# that travels with the table (apcg_core.typetable.Conditions), never a bare catalog index.
FIELDS = ("type_index", "range_m", "elevation", *ATTITUDE)
# The generator's input: NOISE_DIM Gaussian noise values + the len(FIELDS) values of nu (SPEC 7).
NOISE_DIM = 100

FAR_REFERENCE_RANGE_M = 3000.0
NEAR_REFERENCE_RANGE_M = 100.0
# Relative slack of a condition space's bounds (ConditionSpace.check, in_range): it absorbs
# decode(encode(x)) rounding at the ends of a range.
RANGE_SLACK = 1e-12
# A range this close below 3 km is 3 km's (q = 1), not 0.1 km's (q = 30): the space check
# takes values up to RANGE_SLACK x its largest bound below 3 km (1.8e-8 m for Table 1's 18 km,
# 1e-6 m for the largest range any lidar takes), and such a value must not be drawn thirty
# times too small (the cGAN gave 1 point for 751 at 2999.9999999999995 m; probe, stop 54).
REFERENCE_SLACK_M = 1e-6


def reference_range_m(range_m):
    """r0_ref: 3 km when r0 >= 3 km, else 0.1 km (SPEC section 5; the paper's '>' read as '>=',
    3 km less :data:`REFERENCE_SLACK_M` counting as 3 km)."""
    r = np.asarray(range_m, dtype=np.float64)
    out = np.where(r >= FAR_REFERENCE_RANGE_M - REFERENCE_SLACK_M, FAR_REFERENCE_RANGE_M,
                   NEAR_REFERENCE_RANGE_M)
    return float(out) if out.ndim == 0 else out


def in_range(value, lo, hi):
    """Whether ``value`` lies in [lo, hi] as a condition space takes it: within
    :data:`RANGE_SLACK` of the larger bound's magnitude (elementwise on arrays)."""
    slack = RANGE_SLACK * np.maximum(np.abs(lo), np.abs(hi))
    return (value >= lo - slack) & (value <= hi + slack)


def scale_ratio(range_m):
    """q = r0 / r0_ref (paper eq. 2 / 16)."""
    r = np.asarray(range_m, dtype=np.float64)
    out = r / reference_range_m(r)
    return float(out) if np.ndim(out) == 0 else out


# What any condition may be (the one home of these ranges): a range > 0 m, the target below
# the zenith (|elevation| < 90 deg: the observation frame is undefined overhead), pitch within
# [-90, 90] deg and yaw, roll within a turn. Condition checks them; a ConditionSpace's ranges
# and PC2Im / Im2PC's per-sample values (apcg_core.depth) are held to them.
ATTITUDE_LIMITS = {"pitch": math.pi / 2, "yaw": math.pi, "roll": math.pi}  # |angle| <= limit


def _first_bad(values, ok) -> tuple[int, float, int] | None:
    """(index, value, count) of the first of ``values`` (a scalar or an array) not ``ok``."""
    a = np.asarray(values, dtype=np.float64).reshape(-1)
    bad = np.flatnonzero(~ok(a))
    return (int(bad[0]), float(a[bad[0]]), a.size) if len(bad) else None


def _at(i: int, n: int) -> str:
    return f" (sample {i})" if n > 1 else ""


def check_range_m(values) -> None:
    """Refuse a finite range_m (a scalar or one per sample) that no condition takes (<= 0)."""
    bad = _first_bad(values, lambda a: a > 0)
    if bad:
        i, r, n = bad
        raise InputError(f"range_m = {r!r}{_at(i, n)} is out of range; accepted: range_m > 0 "
                         "(metres)")


def check_elevation(values) -> None:
    """Refuse a finite elevation (rad; a scalar or one per sample) that no condition takes:
    the target overhead or beyond (an elevation given in degrees lands here too)."""
    bad = _first_bad(values, lambda a: np.abs(a) < math.pi / 2)
    if bad:
        i, b, n = bad
        where = "overhead" if b > 0 else "straight below"
        raise InputError(
            f"elevation = {b / DEG:.6g} deg{_at(i, n)} puts the target {where} (or beyond); "
            "the observation frame's Z axis is the horizontal direction to the target and is "
            "undefined there. Accepted: -90 deg < elevation < 90 deg")


def check_attitude(name: str, value) -> float:
    """``value`` (rad) if attitude angle ``name`` lies within :data:`ATTITUDE_LIMITS`."""
    limit = ATTITUDE_LIMITS[name]
    return check_range(name, value, -limit, limit, " deg", 1 / DEG)


def degrees_of(rad: float) -> float:
    """``rad`` in degrees, as the shortest decimal whose radians (times DEG) are ``rad``: 60
    deg given as 60 shows as 60, not as 59.99999999999999 (rad / DEG). The degrees a user
    gave lie within a few ulps of rad / DEG, so the shortest of those few that gives ``rad``
    (and of rad / DEG's roundings to fewer digits) is never longer than what was given."""
    d = float(rad) / DEG
    near = [d]
    for direction in (math.inf, -math.inf):
        x = d
        for _ in range(4):
            x = math.nextafter(x, direction)
            near.append(x)
    near += [float(f"{d:.{digits}g}") for digits in range(1, 17)]
    fits = [x for x in near if x * DEG == rad]
    return min(fits, key=lambda x: (len(repr(x)), abs(x - d))) if fits else d


@dataclass(frozen=True)
class Condition:
    """One sample's condition. Angles in radians, range in metres.

    Validation here is physical (finite numbers, a target not overhead, angles within a turn);
    whether a condition lies in a dataset's configured ranges is :meth:`ConditionSpace.check`.
    """

    type_index: int
    range_m: float
    elevation: float
    pitch: float = 0.0
    yaw: float = 0.0
    roll: float = 0.0

    def __post_init__(self) -> None:
        t = self.type_index
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or t < 0:
            raise InputError(f"type_index must be an integer >= 0, got {t!r}")
        object.__setattr__(self, "type_index", int(t))
        check_range_m(check_finite("range_m", self.range_m))
        check_elevation(check_finite("elevation", self.elevation))
        for name in ATTITUDE:
            check_attitude(name, getattr(self, name))
        for name in FIELDS[1:]:
            object.__setattr__(self, name, float(getattr(self, name)))

    @classmethod
    def from_degrees(cls, type_index: int, range_m: float, elevation_deg: float,
                     pitch_deg: float = 0.0, yaw_deg: float = 0.0,
                     roll_deg: float = 0.0) -> Condition:
        return cls(type_index, range_m, elevation_deg * DEG, pitch_deg * DEG,
                   yaw_deg * DEG, roll_deg * DEG)

    def to_degrees(self) -> dict:
        return {"type_index": self.type_index, "range_m": self.range_m,
                **{f"{name}_deg": degrees_of(getattr(self, name))
                   for name in ("elevation", *ATTITUDE)}}

    def as_array(self) -> np.ndarray:
        """[type, r0, beta0, pitch, yaw, roll] as float64 (one row of a condition table)."""
        return np.array([getattr(self, f) for f in FIELDS], dtype=np.float64)

    @classmethod
    def from_array(cls, row) -> Condition:
        row = numbers("a condition row", row)
        if row.shape != (6,):
            raise InputError(f"a condition row has 6 values {FIELDS}, got shape {row.shape}")
        t = row[0]
        if not np.isfinite(t) or t != round(t):
            raise InputError(f"type_index must be an integer, got {t!r}")
        return cls(int(t), *row[1:])

    @property
    def reference_range_m(self) -> float:
        return reference_range_m(self.range_m)

    @property
    def q(self) -> float:
        return scale_ratio(self.range_m)

    @property
    def pose(self) -> tuple[float, float, float, float, float]:
        """(range_m, elevation, pitch, yaw, roll): the arguments of the frames functions."""
        return (self.range_m, self.elevation, self.pitch, self.yaw, self.roll)


def numbers(what: str, values) -> np.ndarray:
    """``values`` as a float64 array, or refused naming ``what`` (a text or an object that is
    not a number would otherwise be a bare numpy error)."""
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what} holds numbers only ({', '.join(FIELDS)}); {exc}") from None


def _deg_pair(lo: float, hi: float) -> tuple[float, float]:
    return (lo * DEG, hi * DEG)


CHECK_ROWS = 65536  # rows checked at once by ConditionSpace.check


@dataclass(frozen=True)
class ConditionSpace:
    """The configured ranges of each condition parameter (the paper's Table 1 by default).

    ``drone_types`` lists the type indices whose range is scaled over ``drone_range_m``;
    every other type uses ``aircraft_range_m``. ``counts`` is the number of values per
    parameter in the dataset grid (Table 1), stored here so the table lives in one place.
    """

    n_types: int = 80
    drone_types: tuple[int, ...] = ()
    aircraft_range_m: tuple[float, float] = (3000.0, 18000.0)
    drone_range_m: tuple[float, float] = (100.0, 600.0)
    elevation: tuple[float, float] = _deg_pair(3.0, 4.0)
    pitch: tuple[float, float] = _deg_pair(1.0, 5.0)
    yaw: tuple[float, float] = _deg_pair(-60.0, 60.0)
    roll: tuple[float, float] = _deg_pair(-5.0, 5.0)
    counts: dict = field(default_factory=lambda: {
        "elevation": 5, "range_m": 10, "yaw": 10, "pitch": 5, "roll": 5})

    def __post_init__(self) -> None:
        object.__setattr__(self, "n_types", check_int("n_types", self.n_types, 1))
        bad = [t for t in self.drone_types if isinstance(t, bool) or not isinstance(t, Integral)
               or not 0 <= t < self.n_types]
        if bad:
            raise InputError(f"drone_types {bad} are not type indices: integers in "
                             f"[0, {self.n_types - 1}]")
        object.__setattr__(self, "drone_types", tuple(sorted(int(t) for t in self.drone_types)))
        for name in ("aircraft_range_m", "drone_range_m", "elevation", "pitch", "yaw", "roll"):
            lo, hi = getattr(self, name)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise InputError(f"range of {name} must be finite with lo < hi, got {(lo, hi)}")
            object.__setattr__(self, name, (float(lo), float(hi)))
        if self.drone_range_m[0] <= 0 or self.aircraft_range_m[0] <= 0:
            raise InputError("ranges must be > 0 m")
        self._check_physical()
        drone = np.zeros(self.n_types, bool)
        drone[list(self.drone_types)] = True
        drone.flags.writeable = False
        object.__setattr__(self, "_drone", drone)  # type index -> in the drone band

    def _check_physical(self) -> None:
        """Each angle range within what a Condition takes (``check`` alone guards the
        tables a model generates from, so a range past it would pass unphysical rows)."""
        for name in ("elevation", *ATTITUDE):
            lo, hi = getattr(self, name)
            try:
                for v in (lo, hi):
                    check_elevation(v) if name == "elevation" else check_attitude(name, v)
            except InputError as exc:
                raise InputError(f"the {name} range [{lo / DEG:.6g}, {hi / DEG:.6g}] deg reaches "
                                 f"past what a condition takes: {exc}") from None

    def is_drone(self, type_index):
        """Whether each type index is one of ``drone_types`` (False for any other value)."""
        t = np.asarray(type_index)
        if t.dtype.kind in "iu" and (not t.size or (t.min() >= 0 and t.max() < self.n_types)):
            return self._drone[t]  # a table lookup: np.isin sorts, 0.1 ms a 256-row block
        return np.isin(t, np.asarray(self.drone_types, dtype=np.int64))

    def range_bounds(self, type_index) -> tuple[np.ndarray, np.ndarray]:
        drone = self.is_drone(type_index)
        lo = np.where(drone, self.drone_range_m[0], self.aircraft_range_m[0])
        hi = np.where(drone, self.drone_range_m[1], self.aircraft_range_m[1])
        return lo, hi

    def bounds(self, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-row (lo, hi) of each of the 6 columns of a condition table (N, 6)."""
        n = table.shape[0]
        lo = np.empty((n, 6))
        hi = np.empty((n, 6))
        lo[:, 0], hi[:, 0] = 0.0, float(self.n_types - 1)
        lo[:, 1], hi[:, 1] = self.range_bounds(table[:, 0].astype(np.int64))
        for j, name in enumerate(FIELDS[2:], start=2):
            lo[:, j], hi[:, j] = getattr(self, name)
        return lo, hi

    def check(self, table, where=None) -> np.ndarray:
        """Return the table (N, 6) as float64 if every value lies in its configured range.

        Raises naming the first bad row, field, value and accepted range. ``where(i, j)``:
        how to name row ``i``'s field ``j`` (a CSV's file, line and column); default
        ``row i``.
        """
        where = where or (lambda i, j: f"row {i}")
        table = np.atleast_2d(numbers("a condition table", table))
        if table.ndim != 2 or table.shape[1] != 6:
            raise InputError(f"a condition table has shape (N, 6) {FIELDS}, got {table.shape}")
        # in blocks of rows: the checks' temporaries stay a few MB for 10^6 conditions
        for start in range(0, len(table), CHECK_ROWS):
            self._check_rows(table[start:start + CHECK_ROWS],
                             lambda i, j, s=start: where(s + i, j))
        return table

    def _check_rows(self, table: np.ndarray, where) -> None:
        nan = ~np.isfinite(table)
        if nan.any():
            i, j = np.argwhere(nan)[0]
            raise InputError(f"{where(i, j)}: {FIELDS[j]} must be finite, got {table[i, j]!r}")
        types = table[:, 0]
        bad = (types != np.round(types)) | (types < 0) | (types > self.n_types - 1)
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(f"{where(i, 0)}: type_index = {types[i]!r} is not a known type; "
                             f"accepted: integers 0 .. {self.n_types - 1}")
        lo, hi = self.bounds(table)
        out = ~in_range(table, lo, hi)
        if out.any():
            i, j = np.argwhere(out)[0]
            scale, unit = (1.0, " m") if j == 1 else ((1 / DEG, " deg") if j > 1 else (1.0, ""))
            v, a, b = table[i, j] * scale, lo[i, j] * scale, hi[i, j] * scale
            band = ""
            if j == 1 and self.drone_types:  # which of the two range bands, and why
                band = (" (the drone band: this type is one of the table's drones)"
                        if self.is_drone(table[i:i + 1, 0])[0] else
                        " (the aircraft band: this type is not one of the table's drones)")
            raise InputError(
                f"{where(i, j)}: {FIELDS[j]} = {distinct(v, a if v < a else b)}{unit} is "
                f"outside the configured range [{a:.6g}{unit}, {b:.6g}{unit}]{band}")

    def encode(self, table) -> np.ndarray:
        """Condition table (N, 6) or one Condition -> nu in [-1, 1] (SPEC section 3)."""
        single = isinstance(table, Condition)
        table = self.check(table.as_array() if single else table)
        lo, hi = self.bounds(table)
        span = np.where(hi > lo, hi - lo, 1.0)  # one type only: its code is -1
        nu = 2.0 * (table - lo) / span - 1.0
        nu = np.clip(nu, -1.0, 1.0)
        return nu[0] if single else nu

    def decode(self, nu) -> np.ndarray:
        """nu (N, 6) in [-1, 1] -> condition table (N, 6) in physical units (m, rad)."""
        nu = np.atleast_2d(numbers("nu", nu))
        if nu.ndim != 2 or nu.shape[-1] != 6:
            raise InputError(f"nu has shape (N, 6), 6 values per row, got shape {nu.shape}")
        if not np.isfinite(nu).all() or (np.abs(nu) > 1.0 + 1e-9).any():
            raise InputError("nu values must be finite and within [-1, 1]")
        table = np.empty_like(nu)
        table[:, 0] = np.rint((nu[:, 0] + 1.0) / 2.0 * (self.n_types - 1))
        lo, hi = self.bounds(table)
        table[:, 1:] = lo[:, 1:] + (nu[:, 1:] + 1.0) / 2.0 * (hi[:, 1:] - lo[:, 1:])
        return table

    def decode_one(self, nu) -> Condition:
        return Condition.from_array(self.decode(nu)[0])

    def to_dict(self) -> dict:
        """Edge representation in degrees and metres (configs, dataset headers)."""
        d = asdict(self)
        for name in ("elevation", "pitch", "yaw", "roll"):
            d[f"{name}_deg"] = [v / DEG for v in d.pop(name)]
        d["drone_types"] = list(self.drone_types)
        d["aircraft_range_m"] = list(self.aircraft_range_m)
        d["drone_range_m"] = list(self.drone_range_m)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> ConditionSpace:
        d = dict(d)
        keys = [f.name for f in fields(cls)]
        keys += [f"{k}_deg" for k in ("elevation", *ATTITUDE)]
        unknown = sorted(set(d) - set(keys), key=str)
        if unknown:
            raise InputError(f"unknown condition space key(s) {', '.join(map(repr, unknown))}; "
                             f"accepted: {', '.join(keys)}")
        for name in ("elevation", "pitch", "yaw", "roll"):
            if f"{name}_deg" in d:
                lo, hi = d.pop(f"{name}_deg")
                d[name] = (lo * DEG, hi * DEG)
        for name in ("aircraft_range_m", "drone_range_m"):
            if name in d:
                d[name] = tuple(d[name])
        d["drone_types"] = tuple(d.get("drone_types", ()))
        return cls(**d)


# A conditions CSV (generate --conditions): these columns, the type by catalog name or index;
# a dataset's conditions.csv (its type_name column) reads as it is.
CSV_COLUMNS = ("type", "range_m", "elevation_deg", "pitch_deg", "yaw_deg", "roll_deg")
# a dataset's conditions.csv (dataset_builder/build.py conditions_csv) also has these: its
# rows' bookkeeping, read past (type_name gives the type; type_code is the dataset's own code)
DATASET_CSV_COLUMNS = ("sample_id", "split", "shard", "type_code", "type_name")
CSV_ACCEPTED = (*CSV_COLUMNS, *DATASET_CSV_COLUMNS)
_CSV_FIELD = {"range_m": "range_m", "elevation": "elevation_deg", "pitch": "pitch_deg",
              "yaw": "yaw_deg", "roll": "roll_deg"}


def read_conditions_csv(path, type_name=str):
    """The rows of a conditions CSV: ``(names, pose, where)``: type names, poses ``(N, 5)``
    (range in metres, then elevation, pitch, yaw, roll in radians) and ``where(i, j)``, the
    file, line, column and value of row ``i``'s condition field ``j`` (for
    :meth:`ConditionSpace.check`). ``type_name(text)`` turns a row's type cell into a type
    name (raising InputError for an unknown one). Read by the project's one CSV reader (a
    byte-order mark, CRLF, quotes, blank lines accepted); every refusal names the file, the
    line, the column and the value. A plain file is read column by column (the fast path);
    anything else, and every refusal, by the careful row-by-row reader. Columns other than
    :data:`CSV_ACCEPTED` are refused (not ignored); a row whose ``type`` and ``type_name``
    name different types is refused."""
    from .io.csv_table import header_names
    header = header_names(path)
    plain = header is not None and set(header) - {""} <= set(CSV_ACCEPTED) \
        and not {"type", "type_name"} <= set(header)
    fast = _read_conditions_fast(path, type_name) if plain else None
    if fast is not None:
        names, pose = fast

        def where(i: int, j: int) -> str:  # only on a refusal: the careful reader says where
            return _read_conditions_careful(path, type_name)[2](i, j)
        return names, pose, where
    return _read_conditions_careful(path, type_name)


def _read_conditions_fast(path, type_name):
    """(names, pose) of a plain conditions CSV read column by column (10^6 rows in a few
    seconds, memory a few arrays), or None when the file or a value needs the careful
    reader's words (it then reads the file, and refuses it naming line and column)."""
    from .io.csv_table import NeedsCare, read_columns

    cols = (("type", "type_name"), *CSV_COLUMNS[1:])
    names: list = []
    parts = []
    try:
        for batch in read_columns(path, cols, numbers=CSV_COLUMNS[1:]):
            try:
                names += each_once(batch["type"], type_name)
            except InputError:
                return None
            parts.append(np.stack([batch[c] for c in CSV_COLUMNS[1:]], axis=1))
    except NeedsCare:
        return None
    if not parts:
        return None
    pose = np.concatenate(parts)
    if not np.isfinite(pose).all():
        return None
    pose[:, 1:] *= DEG
    if _bad_rows(pose).any():
        return None
    return names, pose


def _bad_rows(pose: np.ndarray) -> np.ndarray:
    return (pose[:, 0] <= 0) | (np.abs(pose[:, 1]) >= np.pi / 2) \
        | (np.abs(pose[:, 2]) > np.pi / 2) | (np.abs(pose[:, 3:]) > np.pi).any(axis=1)


def _read_conditions_careful(path, type_name):
    from .io.csv_table import read_csv

    table = read_csv(path, required=CSV_COLUMNS[1:], any_of=[("type", "type_name")],
                     what="conditions CSV", allowed=CSV_ACCEPTED)
    if not table.rows:
        raise InputError(f"{path} has no conditions: only a header (line {table.header_line})")
    type_cols = [c for c in ("type", "type_name") if c in table.header]
    type_col = type_cols[0]
    known: dict = {}
    names, pose = [], np.empty((len(table.rows), 5))

    def named(row, col):
        key = row.text(col)
        if key not in known:
            try:
                known[key] = type_name(key)
            except InputError as exc:
                raise row.error(col, f"is not a type this model knows: {exc}") from None
        return known[key]
    for i, row in enumerate(table.rows):
        found = [named(row, c) for c in type_cols]
        if len(set(found)) > 1:
            raise row.error("type", f"and type_name {row['type_name']!r} name different "
                                    f"types ({found[0]} and {found[1]}); give one of the two "
                                    "columns, or make them agree")
        names.append(found[0])
        pose[i] = [row.float(c) for c in CSV_COLUMNS[1:]]
    pose[:, 1:] *= DEG
    bad = _bad_rows(pose)
    for i in np.flatnonzero(bad)[:1]:  # the first bad row, with the physical check's words
        try:
            Condition(0, *pose[i])
        except InputError as exc:
            column = _CSV_FIELD.get(str(exc).split(" ", 1)[0], "range_m")
            raise table.rows[i].error(column, f"is not accepted: {exc}") from None
    columns = (type_col, *CSV_COLUMNS[1:])

    def where(i: int, j: int) -> str:
        row = table.rows[i]
        return f"{row.where(columns[j])}: {row[columns[j]]!r}"
    return names, pose, where
