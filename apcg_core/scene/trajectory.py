"""A target's pose over time (issue 36): static, read from a CSV file, or made by a generator.

Each kind registers itself in ``KINDS`` (a ``[target.trajectory]`` table's ``kind``) with the
keys it takes; :func:`make_trajectory` builds one from the table. A trajectory answers
``poses(t)`` (seconds, scene time) with scene-frame positions (N, 3) and body -> scene maps
(N, 3, 3) (``poses.py``). Generators start at the target's own pose (its ``range_m``,
``azimuth_deg`` and ``elevation_deg`` are where it is at t = 0) and give the attitude of the
motion: nose along the velocity, banked as a coordinated turn needs. A CSV file gives its own
attitude (the project's pitch, yaw and roll, relative to the line of sight), interpolated
linearly between rows like the position; it is never extrapolated.

Speeds and turns are checked against what the type can fly (``ENVELOPES``): a trajectory
beyond its category's envelope is allowed, with a warning naming the value and the limit.
numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..frames import cartesian_to_spherical
from ..io.csv_table import read_csv
from ..lidar import DEG
from .poses import (
    G_MPS2,
    flight_matrices,
    interpolate_angles,
    pose_value_problem,
    poses_from_angles,
    position_problem,
)


@dataclass(frozen=True)
class Envelope:
    max_speed_mps: float  # true airspeed
    max_load_factor: float  # n; a level coordinated turn's bank b needs n = 1 / cos b


# What each catalog category can fly, round figures at the high end of its members:
#  * speeds: airliners Mmo 0.82-0.89 (A320 0.82, B777 0.89; EASA type certificate data sheets)
#    at 35,000 ft ~ 250-265 m/s; business jets Mmo 0.90-0.935 (G650, Global 7500 TCDS);
#    regional jets Mmo 0.82 (E175); turboprops 360 kt TAS (Q400, the fastest: TCDS); light
#    aircraft Vne 160-200 kt (C172 163 kt, SR22 205 kt: POH); military transports Mach 0.77
#    (C-17, USAF fact sheet); fighters Mach 2+ (F-15 / F-22, USAF fact sheets) at altitude;
#    helicopters Vne 150-193 kt (UH-60 193 kt, CH-47 170 kt: US Army fact files); small fixed
#    wing drones 15-30 m/s and the MQ-9 240 kt (GA-ASI); multirotors 23 m/s (DJI Matrice 300
#    RTK, 21 m/s Mavic 3: DJI specifications).
#  * load factors: transport category 2.5 (14 CFR 25.337), normal category 3.8 (14 CFR 23 as
#    was, 23.337), fighters 9 (F-16 / F-22 design limit), helicopters 3.5 (MIL-S-8698 class
#    figure; assumed for the civil ones), drones 4 (assumed: no certification basis).
ENVELOPES = {
    "airliner_narrowbody": Envelope(265.0, 2.5),
    "airliner_widebody": Envelope(270.0, 2.5),
    "regional_jet": Envelope(250.0, 2.5),
    "business_jet": Envelope(280.0, 2.5),
    "turboprop": Envelope(190.0, 2.5),
    "light_GA": Envelope(105.0, 3.8),
    "military_transport": Envelope(240.0, 2.5),
    "fighter": Envelope(700.0, 9.0),
    "helicopter": Envelope(100.0, 3.5),
    "fixed_wing_drone": Envelope(125.0, 4.0),
    "multirotor_drone": Envelope(25.0, 4.0),
}
# A category not listed: the fastest listed (no warning can be trusted, none is invented).
UNKNOWN_ENVELOPE = Envelope(700.0, 9.0)

# A CSV trajectory's largest step between rows: ADS-B, the data most tracks come from, reports
# an airborne position twice a second (RTCA DO-260B, 2.2.3.2.3), so a step over 1 s means at
# least one report went missing. A table's `max_step_s` overrides it.
MAX_CSV_STEP_S = 1.0


def envelope_warnings(category: str, speed_mps: float, turn_rate: float = 0.0,
                      what: str = "") -> list[str]:
    """Warnings (one line each) where a speed (m/s) or turn rate (rad/s) exceeds the
    category's envelope."""
    env = ENVELOPES.get(category, UNKNOWN_ENVELOPE)
    out = []
    if speed_mps > env.max_speed_mps:
        out.append(f"{what}speed {speed_mps:.4g} m/s exceeds what a {category} flies "
                   f"(about {env.max_speed_mps:g} m/s)")
    bank = math.atan(speed_mps * abs(turn_rate) / G_MPS2)
    if 1.0 / math.cos(bank) > env.max_load_factor:
        limit = math.degrees(G_MPS2 * math.sqrt(env.max_load_factor**2 - 1.0)
                             / max(speed_mps, 1e-9))
        out.append(f"{what}turn rate {math.degrees(abs(turn_rate)):.4g} deg/s at "
                   f"{speed_mps:.4g} m/s needs {1.0 / math.cos(bank):.3g} g; a {category} "
                   f"pulls at most {env.max_load_factor:g} g (about {limit:.3g} deg/s)")
    return out


class Trajectory:
    """A target's poses over time. ``span``: the times it is defined for (seconds)."""

    span = (-math.inf, math.inf)

    def poses(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def warnings(self, category: str, what: str) -> list[str]:
        return []

    def ranges(self, p: np.ndarray) -> np.ndarray:
        """Slant ranges of positions ``p`` (N, 3) this trajectory gave."""
        return np.sqrt((np.asarray(p, np.float64) ** 2).sum(axis=-1))

    def check_times(self, t: np.ndarray, what: str) -> None:
        t = np.asarray(t, np.float64)
        lo, hi = self.span
        if len(t) and (t.min() < lo or t.max() > hi):
            bad = float(t.min() if t.min() < lo else t.max())
            raise InputError(f"{what}: scene time {bad:.6g} s lies outside its trajectory "
                             f"({lo:.6g} s to {hi:.6g} s); a trajectory is not extrapolated")


# --- the kinds ---------------------------------------------------------------------------------
KINDS: dict[str, tuple[type, dict, dict]] = {}  # kind -> (class, required keys, optional keys)


def register(kind: str, required: dict, optional: dict | None = None):
    """Class decorator: a trajectory kind, its required and optional keys (name -> what is
    accepted, for the messages)."""
    def deco(cls):
        KINDS[kind] = (cls, required, optional or {})
        cls.kind = kind
        return cls
    return deco


@dataclass
class Start:
    """The target's pose at t = 0 (its [[target]] table): range, azimuth, elevation (rad)."""

    range_m: float
    azimuth: float
    elevation: float
    attitude: tuple  # (pitch, yaw, roll), rad

    def position(self) -> np.ndarray:
        p, _ = poses_from_angles(self.range_m, self.azimuth, self.elevation, 0.0, 0.0, 0.0)
        return p[0]


class Static(Trajectory):
    """No motion: the [[target]] pose at every time."""

    def __init__(self, start: Start) -> None:
        self.start = start

    def poses(self, t):
        n = len(np.atleast_1d(t))
        s = self.start
        p, b = poses_from_angles(s.range_m, s.azimuth, s.elevation, *s.attitude)
        return np.repeat(p, n, axis=0), np.repeat(b, n, axis=0)

    def ranges(self, p):
        """The range as given, bit for bit (not |p|): a static target alone at azimuth 0 is
        `apcg simulate`'s sample exactly."""
        return np.full(len(p), float(self.start.range_m))


_SPEED = "a speed in m/s > 0"
_ANGLE = "an angle in degrees from -360 to 360"


@register("line", {"speed_mps": _SPEED, "heading_deg": _ANGLE},
          {"climb_deg": "a flight-path angle in degrees from -90 to 90 (default 0: level)"})
class Line(Trajectory):
    """A straight line at constant speed: heading from +Z toward +X (as azimuth), climbing at
    ``climb_deg`` (level by default, the definition of a level pass)."""

    def __init__(self, start: Start, speed_mps, heading_deg, climb_deg=0.0) -> None:
        self.p0 = start.position()
        self.v = float(speed_mps)
        self.heading, self.climb = heading_deg * DEG, climb_deg * DEG

    def velocity(self) -> np.ndarray:
        h, g = self.heading, self.climb
        return self.v * np.array([math.cos(g) * math.sin(h), math.sin(g),
                                  math.cos(g) * math.cos(h)])

    def poses(self, t):
        t = np.atleast_1d(np.asarray(t, np.float64))
        p = self.p0[None] + t[:, None] * self.velocity()[None]
        return p, np.repeat(flight_matrices(self.heading, self.climb, 0.0), len(t), axis=0)

    def warnings(self, category, what):
        return envelope_warnings(category, self.v, 0.0, what)


@register("climb", {"speed_mps": _SPEED, "heading_deg": _ANGLE,
                    "climb_rate_mps": "a vertical speed in m/s, smaller than speed_mps"})
class Climb(Line):
    """A straight climb (or descent) given by its vertical speed."""

    def __init__(self, start: Start, speed_mps, heading_deg, climb_rate_mps) -> None:
        if abs(climb_rate_mps) >= speed_mps:
            raise InputError(f"climb_rate_mps = {climb_rate_mps!r} is not accepted: a "
                             f"vertical speed smaller than speed_mps ({speed_mps!r})")
        super().__init__(start, speed_mps, heading_deg,
                         math.degrees(math.asin(climb_rate_mps / speed_mps)))


@register("turn", {"speed_mps": _SPEED, "heading_deg": _ANGLE,
                   "turn_rate_deg_s": "a rate in deg/s, positive toward +heading (a right turn)"})
class Turn(Trajectory):
    """A level coordinated turn: constant speed and turn rate, banked by atan(v omega / g)."""

    def __init__(self, start: Start, speed_mps, heading_deg, turn_rate_deg_s) -> None:
        self.p0 = start.position()
        self.v = float(speed_mps)
        self.h0, self.omega = heading_deg * DEG, turn_rate_deg_s * DEG
        self.bank = math.atan(self.v * self.omega / G_MPS2)

    def poses(self, t):
        t = np.atleast_1d(np.asarray(t, np.float64))
        h = self.h0 + self.omega * t
        # The chord of the arc flown in t: length v t sin(half) / half, along the mean heading
        # h0 + half. The same as (v / omega) (cos h0 - cos h, sin h - sin h0), without its
        # cancellation: that form lost metres at 1e-13 deg/s and made NaN at 1e-320; this
        # one tends to the straight line as omega -> 0 and is it at omega = 0.
        half = 0.5 * self.omega * t
        chord = self.v * t * np.sinc(half / math.pi)
        mid = self.h0 + half
        p = self.p0[None] + np.stack([chord * np.sin(mid), np.zeros_like(t),
                                      chord * np.cos(mid)], -1)
        return p, flight_matrices(h, 0.0, np.full(len(t), self.bank))

    def warnings(self, category, what):
        return envelope_warnings(category, self.v, self.omega, what)


@register("hover", {"drift_mps": "a drift speed in m/s >= 0",
                    "drift_heading_deg": _ANGLE, "heading_deg": _ANGLE})
class Hover(Trajectory):
    """A multirotor holding its position, level, nose at ``heading_deg``, drifting (wind)
    at ``drift_mps`` toward ``drift_heading_deg``."""

    def __init__(self, start: Start, drift_mps, drift_heading_deg, heading_deg) -> None:
        if drift_mps < 0:
            raise InputError(f"drift_mps = {drift_mps!r} is not accepted: a speed >= 0")
        self.p0 = start.position()
        d = drift_heading_deg * DEG
        self.v = float(drift_mps)
        self.drift = self.v * np.array([math.sin(d), 0.0, math.cos(d)])
        self.heading = heading_deg * DEG

    def poses(self, t):
        t = np.atleast_1d(np.asarray(t, np.float64))
        p = self.p0[None] + t[:, None] * self.drift[None]
        return p, np.repeat(flight_matrices(self.heading, 0.0, 0.0), len(t), axis=0)

    def warnings(self, category, what):
        return envelope_warnings(category, self.v, 0.0, what)


class Sampled(Trajectory):
    """Poses known at times ``t`` (strictly increasing): positions (N, 3, scene frame) and
    attitudes (N, 3: pitch, yaw, roll in rad, relative to the line of sight), interpolated
    linearly between them (angles unwrapped), never extrapolated. A CSV file's rows, or a
    Blender animation evaluated frame by frame (the add-on's Scan Animation)."""

    def __init__(self, t, positions, attitudes) -> None:
        self.t = np.asarray(t, np.float64)
        self.pos = np.asarray(positions, np.float64).reshape(-1, 3)
        self.att = np.asarray(attitudes, np.float64).reshape(-1, 3)
        if len(self.t) < 1 or len(self.pos) != len(self.t) or len(self.att) != len(self.t):
            raise InputError(f"a sampled trajectory needs as many positions and attitudes as "
                             f"times, at least 1; got {len(self.t)}, {len(self.pos)}, "
                             f"{len(self.att)}")
        if len(self.t) > 1 and (np.diff(self.t) <= 0).any():
            raise InputError("a sampled trajectory's times must increase strictly")
        self.span = (float(self.t[0]), float(self.t[-1]))

    def poses(self, t):
        t = np.atleast_1d(np.asarray(t, np.float64))
        p = np.stack([np.interp(t, self.t, self.pos[:, j]) for j in range(3)], -1)
        att = interpolate_angles(self.t, self.att, t)
        az, el, rng = cartesian_to_spherical(p)
        _, b = poses_from_angles(rng, az, el, att[:, 0], att[:, 1], att[:, 2])
        return p, b

    def warnings(self, category, what):
        if len(self.t) < 2:
            return []
        v = np.sqrt((np.diff(self.pos, axis=0) ** 2).sum(1)) / np.diff(self.t)
        return envelope_warnings(category, float(v.max()), 0.0, what)


_POSITION_COLUMNS = (("range_m", "azimuth_deg", "elevation_deg"), ("x_m", "y_m", "z_m"))
_ATTITUDE_COLUMNS = ("pitch_deg", "yaw_deg", "roll_deg")


@register("csv", {"file": "a CSV file (relative to the scene file): t_s, range_m, azimuth_deg, "
                          "elevation_deg or x_m, y_m, z_m, and pitch_deg, yaw_deg, roll_deg"},
          {"max_step_s": f"the largest step between rows in seconds (default {MAX_CSV_STEP_S})"})
class CSVTrack(Sampled):
    """Rows of (t_s, position, attitude): a position as range_m, azimuth_deg, elevation_deg
    (the target's pose angles) or as x_m, y_m, z_m (scene frame), and the attitude relative to
    the line of sight. Interpolated linearly; times strictly increasing, no step over
    ``max_step_s`` (a gap), every cell filled."""

    def __init__(self, start: Start | None, file, max_step_s=MAX_CSV_STEP_S,
                 base_dir: Path | None = None) -> None:
        path = Path(file)
        if base_dir is not None and not path.is_absolute():
            path = base_dir / path
        table = read_csv(path, required=("t_s", *_ATTITUDE_COLUMNS),
                         what="trajectory CSV file",
                         any_of=[("range_m", "x_m")])
        cols = _position_columns(table, path)
        if len(table) < 2:
            raise InputError(f"{path}: {len(table)} row(s); a trajectory needs at least 2 "
                             "rows to interpolate between")
        rows = [_csv_row(row, cols) for row in table]
        data = np.array(rows)
        t = data[:, 0]
        for i in range(1, len(t)):
            if t[i] <= t[i - 1]:
                raise InputError(f"{table.rows[i].where('t_s')}: time {t[i]:g} s does not "
                                 f"increase (the row before is at {t[i - 1]:g} s); a trajectory's "
                                 "times must increase strictly")
            if t[i] - t[i - 1] > max_step_s:
                raise InputError(f"{table.rows[i].where('t_s')}: a gap of {t[i] - t[i - 1]:g} s "
                                 f"after {t[i - 1]:g} s; rows may be at most max_step_s = "
                                 f"{max_step_s:g} s apart (set max_step_s in the trajectory "
                                 "table to allow longer steps)")
        if cols[0] == "range_m":
            pos, _ = poses_from_angles(data[:, 1], data[:, 2] * DEG, data[:, 3] * DEG,
                                       0.0, 0.0, 0.0)
        else:
            pos = data[:, 1:4]
        self.path = path
        super().__init__(t, pos, data[:, 4:7] * DEG)


def _position_columns(table, path: Path) -> tuple:
    """The position columns of a trajectory CSV file's header (one of the two forms, whole),
    after refusing a column no trajectory has (a typo must not drop its values) and a header
    with both forms (one of them would be dropped)."""
    known = ("t_s", *_POSITION_COLUMNS[0], *_POSITION_COLUMNS[1], *_ATTITUDE_COLUMNS)
    accepted = ("t_s, then range_m, azimuth_deg, elevation_deg or x_m, y_m, z_m, then "
                "pitch_deg, yaw_deg, roll_deg")
    for name in table.header:
        if name and name not in known:
            raise InputError(f"{path}, line {table.header_line}, column {table.letter(name)}: "
                             f"unknown column {name!r}; a trajectory CSV file's columns are "
                             f"{accepted}")
    forms = [c for c in _POSITION_COLUMNS if any(n in table.header for n in c)]
    if len(forms) > 1:
        given = [n for c in forms for n in c if n in table.header]
        raise InputError(f"{path}, line {table.header_line}: the header gives the position "
                         f"twice ({', '.join(given)}); accepted: range_m, azimuth_deg, "
                         "elevation_deg or x_m, y_m, z_m, not both")
    cols = forms[0]
    missing = [c for c in cols if c not in table.header]
    if missing:
        raise InputError(f"{path}, line {table.header_line}: the header has "
                         f"{', '.join(c for c in cols if c in table.header)} but no "
                         f"{', '.join(missing)}; a position is {', '.join(cols)}")
    return cols


def _csv_row(row, cols: tuple) -> list:
    """One trajectory CSV row's numbers (t_s, the position, the attitude), each pose value
    checked by the rule a [[target]] table's key of the same name has (poses.POSE_RULES)."""
    out = [row.float("t_s")]
    for c in (*cols, *_ATTITUDE_COLUMNS):
        v = row.float(c)
        why = pose_value_problem(c, v)
        if why is not None:
            raise row.error(c, why)
        out.append(v)
    if cols[0] == "x_m":
        why = position_problem(out[1:4])
        if why is not None:
            raise InputError(f"{row.where()}: the position ({', '.join(row[c] for c in cols)}) "
                             f"{why}")
    return out


def make_trajectory(table: dict | None, start: Start, source: str,
                    base_dir: Path | None = None) -> Trajectory:
    """The trajectory of a [[target]] (its ``trajectory`` table, or None: static)."""
    if table is None:
        return Static(start)
    if not isinstance(table, dict):
        raise InputError(f"{source}: trajectory must be a table with a kind ({', '.join(KINDS)})"
                         f", got {table!r}")
    kind = table.get("kind")
    if kind not in KINDS:
        raise InputError(f"{source}: trajectory kind {kind!r} is unknown; accepted: "
                         f"{', '.join(KINDS)}")
    cls, required, optional = KINDS[kind]
    keys = {k: v for k, v in table.items() if k != "kind"}
    unknown = sorted(set(keys) - set(required) - set(optional))
    if unknown:
        raise InputError(f"{source}: unknown key(s) {', '.join(unknown)} in a {kind} "
                         f"trajectory; accepted: {', '.join([*required, *optional])}")
    missing = [k for k in required if k not in keys]
    if missing:
        raise InputError(f"{source}: a {kind} trajectory needs {', '.join(missing)} ("
                         + "; ".join(f"{k}: {required[k]}" for k in missing) + ")")
    for k, v in keys.items():
        if k == "file":
            if not isinstance(v, str) or not v.strip():
                raise InputError(f"{source}: trajectory file = {v!r} is not accepted: "
                                 f"{required[k]}")
            continue
        ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
        if ok and k.endswith("_deg") and k != "turn_rate_deg_s":
            ok = abs(v) <= (90 if k == "climb_deg" else 360)
        if ok and k in ("speed_mps", "max_step_s"):
            ok = v > 0
        if not ok:
            spec = {**required, **optional}[k]
            raise InputError(f"{source}: trajectory {k} = {v!r} is not accepted: {spec}")
    try:
        if kind == "csv":
            return cls(start, base_dir=base_dir, **keys)
        return cls(start, **keys)
    except InputError as exc:
        msg = str(exc)
        raise InputError(msg if str(source) in msg else f"{source}: {msg}") from None


__all__ = ["ENVELOPES", "KINDS", "Sampled", "Start", "Static", "Trajectory",
           "envelope_warnings", "make_trajectory", "register"]
