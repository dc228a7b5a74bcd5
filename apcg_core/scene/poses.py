"""Poses of a scene's targets (issue 36): where each aircraft is and how it is turned, in the
**scene frame**, and the conversions to and from the project's pose angles (SPEC section 2).

Scene frame: origin at the lidar, Y vertical up, Z horizontal at azimuth 0, X horizontal to the
right looking along +Z: the observation frame of SPEC section 2 of a target at azimuth 0. A
target at azimuth a is that target's own observation frame turned about Y by a (+Z toward
+X), so a pose given as (range, azimuth, elevation, pitch, yaw, roll) keeps the project's
meaning of the attitude: relative to the target's own line of sight (zero attitude: the nose
points at the lidar).

A pose is a position P (3,) and the linear map B (3, 3) from the body frame (x nose, y left
wing, z up) to the scene frame: a body point p sits at P + B p. B has determinant -1 (the
scene frame is left-handed as numbers, as the observation frame is). Batched: (N, 3) and
(N, 3, 3). numpy only.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..frames import (
    M0,
    attitude_angles,
    body_to_observation_matrices,
    cartesian_to_spherical,
    target_centres,
)
from ..options import RULES, Rule

# What a target's pose value accepts, wherever it is given: a [[target]] table's keys and a
# trajectory CSV file's columns. The pose angles' rules are the command line's own
# (``apcg simulate --range-m ...``: options.RULES, one table); a scene-frame position's
# coordinates are bounded by range_m's limit. An elevation of +-90 deg passes the rule and is
# refused by :func:`pose_value_problem` (straight overhead has no horizontal direction).
POSE_ANGLES = ("range_m", "azimuth_deg", "elevation_deg", "pitch_deg", "yaw_deg", "roll_deg")
POSITION_XYZ = ("x_m", "y_m", "z_m")
POSE_RULES: dict[str, Rule] = {
    **{k: RULES[k] for k in POSE_ANGLES},
    **{k: Rule("a finite coordinate in metres from -1e6 to 1e6", lo=-1e6, hi=1e6)
       for k in POSITION_XYZ},
}
OVERHEAD = ("an elevation strictly between -90 and 90 deg (a target straight overhead has no "
            "horizontal direction: SPEC section 2)")


def pose_value_problem(name: str, value) -> str | None:
    """Why ``value`` is refused as the pose value ``name`` (a key of POSE_RULES): "is not
    accepted: WHAT IS ACCEPTED", or None when it is accepted."""
    rule = POSE_RULES[name]
    number = isinstance(value, int | float) and not isinstance(value, bool)
    if not number or not rule.ok(float(value)):
        return f"is not accepted: {rule.accepted}"
    if name == "elevation_deg" and abs(value) >= 90:
        return f"is not accepted: {OVERHEAD}"
    return None


def position_problem(p) -> str | None:
    """Why a scene-frame position (3,) is refused as a target's place: its range by
    range_m's rule, straight overhead by elevation_deg's; None when accepted."""
    x, y, z = (float(v) for v in p)
    r = float(np.sqrt(x * x + y * y + z * z))
    if not POSE_RULES["range_m"].ok(r):
        return f"lies {r:.6g} m from the lidar; accepted: {POSE_RULES['range_m'].accepted}"
    if x == 0.0 and z == 0.0:
        return f"lies straight above or below the lidar; accepted: {OVERHEAD}"
    return None


# Gravity for the bank of a coordinated turn (tan(bank) = v omega / g): standard gravity,
# 9.80665 m/s^2 (CGPM 1901, the value ISO 80000-3 keeps).
G_MPS2 = 9.80665


def azimuth_turns(azimuth) -> np.ndarray:
    """(N, 3, 3) turns about the vertical Y by ``azimuth`` (rad): +Z toward +X, so that a point
    at azimuth a moves to azimuth a + azimuth (frames._rot_y, batched)."""
    a = np.atleast_1d(np.asarray(azimuth, np.float64))
    c, s = np.cos(a), np.sin(a)
    out = np.zeros((len(a), 3, 3))
    out[:, 0, 0] = c
    out[:, 0, 2] = s
    out[:, 1, 1] = 1.0
    out[:, 2, 0] = -s
    out[:, 2, 2] = c
    return out


def turn(azimuth, m: np.ndarray) -> np.ndarray:
    """Matrices or points (N, 3, 3) / (N, 3) turned about Y by ``azimuth`` (one or N values).
    An azimuth of exactly 0 returns ``m`` itself, bit for bit (a scene of one target at
    azimuth 0 is `apcg simulate`'s geometry to the last bit)."""
    a = np.broadcast_to(np.asarray(azimuth, np.float64), (len(m),))
    if not a.any():
        return m
    r = azimuth_turns(a)
    if m.ndim == 2:
        return np.einsum("nij,nj->ni", r, m)
    return r @ m


def poses_from_angles(range_m, azimuth, elevation, pitch, yaw, roll):
    """Scene-frame poses (P, B) of targets given as the project's pose angles (radians, metres;
    the attitude relative to each target's line of sight)."""
    range_m, azimuth, elevation, pitch, yaw, roll = np.broadcast_arrays(
        *(np.atleast_1d(np.asarray(a, np.float64)) for a in (range_m, azimuth, elevation,
                                                            pitch, yaw, roll)))
    b = body_to_observation_matrices(pitch, yaw, roll)
    p = target_centres(range_m, elevation)
    return turn(azimuth, p), turn(azimuth, b)


def angles_of_poses(p: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Inverse of :func:`poses_from_angles`: (N, 6) [range, azimuth, elevation, pitch, yaw,
    roll] (metres, radians) of scene-frame poses."""
    p = np.atleast_2d(np.asarray(p, np.float64))
    b = np.asarray(b, np.float64).reshape(-1, 3, 3)
    az, el, r = cartesian_to_spherical(p)
    if (r <= 0).any():
        raise InputError("a target sits on the lidar: it has no range or direction")
    att = np.linalg.inv(M0)[None] @ azimuth_turns(-az) @ b
    out = np.empty((len(p), 6))
    out[:, 0], out[:, 1], out[:, 2] = r, az, el
    for i in range(len(p)):
        out[i, 3:] = attitude_angles(att[i])
    return out


def flight_matrices(heading, flight_path, bank) -> np.ndarray:
    """(N, 3, 3) body -> scene maps of aircraft flying along ``heading`` (from +Z toward +X,
    as azimuth), climbing at ``flight_path`` (above the horizontal) and banked by ``bank``
    (positive: right wing down, the bank of a turn toward +heading). Radians."""
    h, g, f = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, np.float64))
                                    for a in (heading, flight_path, bank)))
    ch, sh, cg, sg, cf, sf = np.cos(h), np.sin(h), np.cos(g), np.sin(g), np.cos(f), np.sin(f)
    nose = np.stack([cg * sh, sg, cg * ch], -1)
    left0 = np.stack([-ch, np.zeros_like(h), sh], -1)
    up0 = np.stack([-sg * sh, cg, -sg * ch], -1)
    left = cf[:, None] * left0 + sf[:, None] * up0
    up = cf[:, None] * up0 - sf[:, None] * left0
    return np.stack([nose, left, up], axis=-1)  # columns: where body x, y, z go


def interpolate_angles(t_known: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear interpolation of angle columns (N, k) in radians, each unwrapped first so that a
    yaw crossing +-180 deg turns the short way."""
    un = np.unwrap(values, axis=0)
    return np.stack([np.interp(t, t_known, un[:, j]) for j in range(un.shape[1])], -1)
