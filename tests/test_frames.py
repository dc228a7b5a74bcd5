import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from apcg_core.frames import (
    ATTITUDE,
    M0,
    POSE_NAMES,
    attitude_angles,
    attitude_matrix,
    blender_to_observation,
    body_to_observation,
    body_to_observation_matrix,
    cartesian_to_spherical,
    directions_to_body,
    lidar_local_to_observation,
    observation_to_blender,
    observation_to_body,
    observation_to_lidar_local,
    pose_from_lidar_local,
    spherical_to_cartesian,
    target_centre,
    target_matrix_lidar_local,
)

DEG = math.pi / 180
NOSE, LEFT, UP = np.eye(3)
RIGHT = -LEFT
angle = st.floats(-math.pi, math.pi)
small = st.floats(-80 * DEG, 80 * DEG)
coord = st.floats(-1e4, 1e4)


def elev(v):
    return math.degrees(math.atan2(v[1], math.hypot(v[0], v[2])))


def test_zero_attitude_points_the_nose_at_the_lidar():
    m = body_to_observation_matrix(0, 0, 0)
    np.testing.assert_allclose(m @ NOSE, [0, 0, -1], atol=1e-15)  # toward the lidar, horizontal
    np.testing.assert_allclose(m @ UP, [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(m @ LEFT, [1, 0, 0], atol=1e-15)


def test_handedness_changes_only_in_m0():
    assert np.linalg.det(M0) == pytest.approx(-1.0)
    r = attitude_matrix(pitch=-0.2, yaw=0.3, roll=1.1)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-14)


@pytest.mark.parametrize("pitch_deg", [1.0, 5.0, 30.0])
def test_positive_pitch_raises_the_nose(pitch_deg):
    nose = body_to_observation_matrix(pitch=pitch_deg * DEG, yaw=0, roll=0) @ NOSE
    assert nose[1] > 0
    assert elev(nose) == pytest.approx(pitch_deg)
    assert body_to_observation_matrix(pitch=-pitch_deg * DEG, yaw=0, roll=0)[1] @ NOSE < 0


@pytest.mark.parametrize("yaw_deg", [1.0, 13.2, 60.0])
def test_positive_yaw_swings_the_nose_toward_plus_x(yaw_deg):
    nose = body_to_observation_matrix(pitch=0, yaw=yaw_deg * DEG, roll=0) @ NOSE
    assert nose[0] > 0
    assert math.degrees(math.atan2(nose[0], -nose[2])) == pytest.approx(yaw_deg)
    assert (body_to_observation_matrix(pitch=0, yaw=-yaw_deg * DEG, roll=0) @ NOSE)[0] < 0


@pytest.mark.parametrize("roll_deg", [0.13, 5.0, 40.0])
def test_positive_roll_lowers_the_right_wing(roll_deg):
    m = body_to_observation_matrix(pitch=0, yaw=0, roll=roll_deg * DEG)
    assert (m @ RIGHT)[1] < 0 and (m @ LEFT)[1] > 0
    assert elev(m @ RIGHT) == pytest.approx(-roll_deg)
    np.testing.assert_allclose(m @ NOSE, [0, 0, -1], atol=1e-15)  # roll leaves the nose alone


@given(yaw=angle, pitch=small, roll=angle)
def test_intrinsic_order_nose_elevation_is_the_pitch(yaw, pitch, roll):
    # Yaw is applied last about the vertical, roll first about the nose: neither changes how
    # far the nose is raised, and the nose's heading is the yaw.
    nose = body_to_observation_matrix(pitch=pitch, yaw=yaw, roll=roll) @ NOSE
    assert elev(nose) == pytest.approx(math.degrees(pitch), abs=1e-9)
    if abs(pitch) < 89 * DEG:
        assert math.atan2(nose[0], -nose[2]) == pytest.approx(yaw, abs=1e-9)


def test_roll_then_pitch_then_yaw():
    # With 90 deg yaw and 90 deg roll the wing that roll lowered stays low after the yaw:
    # roll happens about the body axis, before yaw (intrinsic yaw-pitch-roll).
    m = body_to_observation_matrix(pitch=0, yaw=90 * DEG, roll=90 * DEG)
    np.testing.assert_allclose(m @ RIGHT, [0, -1, 0], atol=1e-15)
    np.testing.assert_allclose(m @ NOSE, [1, 0, 0], atol=1e-15)


@given(r0=st.floats(50, 20000), b0=st.floats(-89 * DEG, 89 * DEG))
def test_centre_lands_where_spec_says(r0, b0):
    c = body_to_observation(np.zeros(3), r0, b0, pitch=0.05, yaw=0.4, roll=-0.1)
    np.testing.assert_allclose(c, [0, r0 * math.sin(b0), r0 * math.cos(b0)], rtol=1e-15,
                               atol=1e-9)
    np.testing.assert_allclose(c, target_centre(r0, b0))
    a, b, r = cartesian_to_spherical(c)
    assert a == pytest.approx(0.0, abs=1e-15) and b == pytest.approx(b0) and r == pytest.approx(r0)


@given(a=st.floats(-3.1, 3.1), b=st.floats(-1.55, 1.55), r=st.floats(1e-3, 2e4))
def test_spherical_cartesian_round_trip(a, b, r):
    xyz = spherical_to_cartesian(a, b, r)
    a2, b2, r2 = cartesian_to_spherical(xyz)
    assert r2 == pytest.approx(r, rel=1e-14)
    assert b2 == pytest.approx(b, abs=1e-12)
    assert a2 == pytest.approx(a, abs=1e-12)
    np.testing.assert_allclose(spherical_to_cartesian(a2, b2, r2), xyz, rtol=1e-13, atol=1e-9)


def test_spherical_axes():
    np.testing.assert_allclose(spherical_to_cartesian(0, 0, 5), [0, 0, 5])
    np.testing.assert_allclose(spherical_to_cartesian(math.pi / 2, 0, 5), [5, 0, 0], atol=1e-15)
    np.testing.assert_allclose(spherical_to_cartesian(0, math.pi / 2, 5), [0, 5, 0], atol=1e-15)


@given(p=st.lists(st.tuples(coord, coord, coord), min_size=1, max_size=20),
       r0=st.floats(50, 18000), b0=st.floats(-1.5, 1.5), yaw=angle, pitch=small, roll=angle)
def test_body_observation_round_trip(p, r0, b0, yaw, pitch, roll):
    p = np.array(p)
    obs = body_to_observation(p, r0, b0, pitch=pitch, yaw=yaw, roll=roll)
    back = observation_to_body(obs, r0, b0, pitch=pitch, yaw=yaw, roll=roll)
    np.testing.assert_allclose(back, p, atol=1e-8)
    # distances are preserved (a rigid motion)
    np.testing.assert_allclose(np.linalg.norm(obs - target_centre(r0, b0), axis=1),
                               np.linalg.norm(p, axis=1), rtol=1e-12, atol=1e-9)
    d = directions_to_body(obs - target_centre(r0, b0), pitch=pitch, yaw=yaw, roll=roll)
    np.testing.assert_allclose(d, p, atol=1e-8)


@given(p=st.lists(st.tuples(coord, coord, coord), min_size=1, max_size=20))
def test_observation_blender_round_trip(p):
    p = np.array(p)
    bl = observation_to_blender(p)
    np.testing.assert_array_equal(blender_to_observation(bl), p)
    np.testing.assert_array_equal(observation_to_blender(blender_to_observation(p)), p)


def test_blender_axes():
    # obs X -> Blender x, obs Y (up) -> Blender z (up), obs Z (away) -> Blender y (lidar looks +Y)
    np.testing.assert_array_equal(observation_to_blender([1, 2, 3]), [1, 3, 2])
    # a right-handed Blender frame: x cross y = z must hold for the mapped basis
    ex, ey, ez = (observation_to_blender(v) for v in np.eye(3))
    np.testing.assert_array_equal(np.cross(ex, ez), ey)  # X x Z(obs) -> up in Blender


turn = st.floats(-3.1, 3.1)


@given(st.floats(100.0, 18000.0), st.floats(-1.5, 1.5), turn, st.floats(-1.55, 1.55), turn,
       turn)
def test_target_matrix_and_pose_round_trip(r0, b0, yaw, pitch, roll, az):
    m = target_matrix_lidar_local(r0, b0, pitch=pitch, yaw=yaw, roll=roll, azimuth=az)
    assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0, abs=1e-9)  # a proper rotation
    p = pose_from_lidar_local(m)
    assert tuple(p) == POSE_NAMES
    got = [p[k] for k in ("range_m", "elevation", "azimuth", "yaw", "pitch", "roll")]
    assert np.allclose(got, [r0, b0, az, yaw, pitch, roll], rtol=0, atol=1e-8)
    body = np.array([[10.0, 2.0, -1.0], [-3.0, 5.0, 0.5]])
    local = observation_to_lidar_local(
        body_to_observation(body, r0, b0, pitch=pitch, yaw=yaw, roll=roll), az)
    assert np.allclose(local, body @ m[:3, :3].T + m[:3, 3], atol=1e-7)
    assert np.allclose(lidar_local_to_observation(local, az),
                       body_to_observation(body, r0, b0, pitch=pitch, yaw=yaw, roll=roll),
                       atol=1e-7)


def test_target_matrix_axes():
    # zero azimuth and attitude: the nose points back at the lidar (local -Y), up is local +Z,
    # the centre sits along the lidar's line of sight (+Y) at the elevation
    m = target_matrix_lidar_local(1000.0, 0.1, 0.0, 0.0, 0.0)
    assert np.allclose(m[:3, 0], [0, -1, 0]) and np.allclose(m[:3, 2], [0, 0, 1])
    assert np.allclose(m[:3, 3], [0, 1000 * math.cos(0.1), 1000 * math.sin(0.1)])
    # +azimuth swings the target toward the lidar's right (+x)
    assert target_matrix_lidar_local(1000.0, 0.0, 0.0, 0.0, 0.0, azimuth=0.2)[0, 3] > 0
    # angles come back in the one order, ATTITUDE (pitch, yaw, roll)
    assert ATTITUDE == ("pitch", "yaw", "roll")
    assert attitude_angles(attitude_matrix(pitch=-0.2, yaw=0.3, roll=0.1)) == pytest.approx(
        (-0.2, 0.3, 0.1))
    with pytest.raises(ValueError, match="sits on the lidar"):
        pose_from_lidar_local(np.eye(4))
