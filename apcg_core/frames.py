"""Frames of SPEC section 2: observation (left-handed as numbers), body, Blender lidar-local.

All functions take and return float64 arrays with the coordinate on the last axis.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError

# The one angle order (SPEC section 3): every attitude triple, positional or in a file, comes
# as (pitch, yaw, roll), the order of nu. A target's pose adds its range and elevation in front
# and, in Blender only, the azimuth about the lidar's vertical behind.
ATTITUDE = ("pitch", "yaw", "roll")
POSE_NAMES = ("range_m", "elevation", *ATTITUDE, "azimuth")

# Body (x nose, y left wing, z up) -> observation (X right, Y up, Z away from the lidar) at
# zero attitude: nose -> -Z, left wing -> +X, up -> +Y. det = -1: the one place where the
# handedness changes.
M0 = np.array([[0.0, 1.0, 0.0],
               [0.0, 0.0, 1.0],
               [-1.0, 0.0, 0.0]])


def _f64(a) -> np.ndarray:
    return np.asarray(a, dtype=np.float64)


def spherical_to_cartesian(alpha, beta, r) -> np.ndarray:
    """(azimuth, elevation, slant range) -> observation (x, y, z); SPEC section 2."""
    alpha, beta, r = np.broadcast_arrays(_f64(alpha), _f64(beta), _f64(r))
    cb = np.cos(beta)
    return np.stack([r * cb * np.sin(alpha), r * np.sin(beta), r * cb * np.cos(alpha)], axis=-1)


def cartesian_to_spherical(xyz):
    """Observation (x, y, z) -> (azimuth, elevation, slant range), each shaped like xyz[..., 0]."""
    xyz = _f64(xyz)
    if xyz.shape[-1:] != (3,):  # a 2-vector would fail on its missing z; 4 would drop one
        raise InputError(f"points have (x, y, z) on the last axis, got shape {xyz.shape}")
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    horizontal = np.hypot(x, z)
    return np.arctan2(x, z), np.arctan2(y, horizontal), np.sqrt(horizontal**2 + y**2)


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def attitude_matrix(pitch: float, yaw: float, roll: float) -> np.ndarray:
    """Body-frame attitude R(phi, theta, gamma): intrinsic yaw-pitch-roll (roll applied first).

    Arguments come in ATTITUDE order (pitch, yaw, roll), the order of nu, like every angle
    triple in the project; the order in which the rotations are applied is another matter.

    Signs by effect: +pitch raises the nose (a rotation about the body's right axis, i.e. -y),
    +yaw turns the nose toward the left wing (+z axis), +roll lowers the right wing (+x axis).
    """
    return _rot_z(yaw) @ _rot_y(-pitch) @ _rot_x(roll)


def body_to_observation_matrix(pitch: float, yaw: float, roll: float) -> np.ndarray:
    """The linear part M0 @ R of the body -> observation map."""
    return M0 @ attitude_matrix(pitch, yaw, roll)


def target_centre(range_m: float, elevation: float) -> np.ndarray:
    """Observation-frame position of the centre of mass: (0, r0 sin b0, r0 cos b0)."""
    return spherical_to_cartesian(0.0, elevation, range_m)


def body_to_observation(points, range_m: float, elevation: float,
                        pitch: float, yaw: float, roll: float) -> np.ndarray:
    """Body-frame points -> observation frame: C + M0 @ R @ p (SPEC section 2)."""
    m = body_to_observation_matrix(pitch, yaw, roll)
    return _f64(points) @ m.T + target_centre(range_m, elevation)


def observation_to_body(points, range_m: float, elevation: float,
                        pitch: float, yaw: float, roll: float) -> np.ndarray:
    """Inverse of :func:`body_to_observation` (M0 @ R is orthogonal: inverse = transpose)."""
    m = body_to_observation_matrix(pitch, yaw, roll)
    return (_f64(points) - target_centre(range_m, elevation)) @ m


def directions_to_body(dirs, pitch: float, yaw: float, roll: float) -> np.ndarray:
    """Observation-frame direction vectors -> body-frame directions (no translation)."""
    return _f64(dirs) @ body_to_observation_matrix(pitch, yaw, roll)


# Blender lidar-local: x = obs X, y = obs Z (the lidar looks along local +Y), z = obs Y (up).
_SWAP_YZ = [0, 2, 1]


def observation_to_blender(points) -> np.ndarray:
    """Observation frame -> the lidar object's local frame in Blender (right-handed, Z up)."""
    return _f64(points)[..., _SWAP_YZ]


def blender_to_observation(points) -> np.ndarray:
    """The lidar object's local frame in Blender -> observation frame."""
    return _f64(points)[..., _SWAP_YZ]


def body_to_observation_matrices(pitch, yaw, roll) -> np.ndarray:
    """Batched :func:`body_to_observation_matrix`: arrays of N angles -> (N, 3, 3)."""
    pitch, yaw, roll = (np.atleast_1d(_f64(a)) for a in (pitch, yaw, roll))
    n = len(yaw)

    def stack(rows):
        return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)

    z, o = np.zeros(n), np.ones(n)
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(-pitch), np.sin(-pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    rz = stack([[cy, -sy, z], [sy, cy, z], [z, z, o]])
    ry = stack([[cp, z, sp], [z, o, z], [-sp, z, cp]])
    rx = stack([[o, z, z], [z, cr, -sr], [z, sr, cr]])
    return M0 @ rz @ ry @ rx


def target_centres(range_m, elevation) -> np.ndarray:
    """Batched :func:`target_centre`: (N, 3)."""
    return spherical_to_cartesian(0.0, np.atleast_1d(_f64(elevation)),
                                  np.atleast_1d(_f64(range_m)))


def attitude_angles(r) -> tuple[float, float, float]:
    """Inverse of :func:`attitude_matrix`: (pitch, yaw, roll) of a rotation matrix.

    Pitch is in [-90, 90] deg; at exactly +-90 deg yaw and roll are not separable and roll is
    returned as 0."""
    r = _f64(r)
    pitch = float(np.arcsin(np.clip(r[2, 0], -1.0, 1.0)))
    if abs(r[2, 0]) > 1.0 - 1e-12:
        return pitch, float(np.arctan2(-r[0, 1], r[1, 1])), 0.0
    return pitch, float(np.arctan2(r[1, 0], r[0, 0])), float(np.arctan2(r[2, 1], r[2, 2]))


def _azimuth_matrix(azimuth: float) -> np.ndarray:
    """Turns the observation frame about its vertical (Y) by ``azimuth``: +Z toward +X."""
    return _rot_y(azimuth)


_SWAP = np.eye(3)[_SWAP_YZ]  # the observation <-> Blender lidar-local permutation


def target_matrix_lidar_local(range_m: float, elevation: float, pitch: float, yaw: float,
                              roll: float, azimuth: float = 0.0) -> np.ndarray:
    """4 x 4 map from the body frame to the lidar object's local frame in Blender.

    ``azimuth`` (not part of the condition) turns the target about the lidar's vertical: the
    lidar tracks each target, so its observation frame is this one turned back by ``azimuth``.
    """
    out = np.eye(4)
    turn = _azimuth_matrix(azimuth)
    out[:3, :3] = _SWAP @ turn @ body_to_observation_matrix(pitch, yaw, roll)
    out[:3, 3] = _SWAP @ turn @ target_centre(range_m, elevation)
    return out


def pose_from_lidar_local(matrix) -> dict:
    """Inverse of :func:`target_matrix_lidar_local`: a dict of POSE_NAMES (metres, radians)
    of a body-to-lidar-local matrix (scale is removed)."""
    m = _f64(matrix)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise InputError(f"a pose matrix is 4 x 4 and finite, got shape {m.shape}"
                         f"{'' if m.shape != (4, 4) else ' with NaN or inf'}")
    obs = _SWAP @ m[:3, 3]
    azimuth, elevation, range_m = (float(v) for v in cartesian_to_spherical(obs))
    if range_m <= 0.0 or not np.isfinite(range_m):
        raise InputError("the target sits on the lidar: no range or direction")
    lin = _SWAP @ m[:3, :3]
    scale = np.linalg.norm(lin, axis=0, keepdims=True)
    if not (scale > 0).all():  # scale 0 on an axis: no attitude to read (NaN angles)
        raise InputError(f"the pose matrix has scale {scale.ravel().tolist()} on its body "
                         "axes: a zero scale leaves no attitude to read")
    lin = lin / scale
    att = np.linalg.inv(M0) @ _azimuth_matrix(azimuth).T @ lin
    pitch, yaw, roll = attitude_angles(att)
    return {"range_m": range_m, "elevation": elevation, "pitch": pitch, "yaw": yaw,
            "roll": roll, "azimuth": azimuth}


def observation_to_lidar_local(points, azimuth: float = 0.0) -> np.ndarray:
    """Points of a target's observation frame -> the lidar's local frame (see azimuth above)."""
    return _f64(points) @ (_SWAP @ _azimuth_matrix(azimuth)).T


def lidar_local_to_observation(points, azimuth: float = 0.0) -> np.ndarray:
    """Inverse of :func:`observation_to_lidar_local`."""
    return _f64(points) @ (_SWAP @ _azimuth_matrix(azimuth))
