"""The attitude loop's quaternion helpers against closed-form answers (FRD/NED, w-x-y-z)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.control.quaternion import (
    body_z_ned,
    canonical,
    euler_to_quat,
    ned_down_frd,
    normalise_or_none,
    quat_conj,
    quat_log,
    quat_mul,
    shortest_arc,
    yaw_rad,
)

angle = st.floats(-3.0, 3.0)


def rotate(q: tuple[float, float, float, float], v: tuple[float, float, float]) -> np.ndarray:
    """``q ⊗ (0, v) ⊗ q*``: body vector into the world."""
    r = quat_mul(quat_mul(q, (0.0, *v)), quat_conj(q))
    return np.array(r[1:])


def test_euler_roll_tilts_body_down_to_the_left() -> None:
    # Roll right by phi: body z (down) leans to the left, (0, -sin phi, cos phi) in NED.
    phi = math.radians(30.0)
    q = euler_to_quat(phi, 0.0, 0.0)
    np.testing.assert_allclose(body_z_ned(q), (0.0, -math.sin(phi), math.cos(phi)), atol=1e-15)
    np.testing.assert_allclose(rotate(q, (0.0, 0.0, 1.0)), body_z_ned(q), atol=1e-15)


def test_euler_pitch_up_tilts_body_down_backward() -> None:
    th = math.radians(20.0)
    q = euler_to_quat(0.0, th, 0.0)
    np.testing.assert_allclose(body_z_ned(q), (math.sin(th), 0.0, math.cos(th)), atol=1e-15)


@given(angle, st.floats(-1.5, 1.5), angle)
def test_yaw_of_euler_is_the_yaw(roll: float, pitch: float, yaw: float) -> None:
    assert yaw_rad(euler_to_quat(roll, pitch, yaw)) == pytest.approx(yaw, abs=1e-9)


@given(angle, st.floats(-1.5, 1.5), angle)
def test_ned_down_in_body_is_the_inverse_rotation(roll: float, pitch: float, yaw: float) -> None:
    q = euler_to_quat(roll, pitch, yaw)
    down_in_body = rotate(quat_conj(q), (0.0, 0.0, 1.0))
    np.testing.assert_allclose(ned_down_frd(q), down_in_body, atol=1e-12)


def test_quat_log_is_axis_times_angle_the_short_way() -> None:
    # 350 deg about z is -10 deg about z.
    q = (math.cos(math.radians(175.0)), 0.0, 0.0, math.sin(math.radians(175.0)))
    np.testing.assert_allclose(quat_log(q), (0.0, 0.0, math.radians(-10.0)), atol=1e-12)
    np.testing.assert_allclose(quat_log((1.0, 0.0, 0.0, 0.0)), (0.0, 0.0, 0.0))
    # pi about x: angle pi, finite.
    np.testing.assert_allclose(quat_log((0.0, 1.0, 0.0, 0.0)), (math.pi, 0.0, 0.0), atol=1e-12)


@given(st.floats(-3.1, 3.1), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0))
def test_quat_log_inverts_the_exponential(theta: float, ax: float, ay: float, az: float) -> None:
    n = math.sqrt(ax * ax + ay * ay + az * az)
    if n < 1e-3:
        return
    axis = (ax / n, ay / n, az / n)
    s = math.sin(0.5 * theta)
    q = (math.cos(0.5 * theta), s * axis[0], s * axis[1], s * axis[2])
    np.testing.assert_allclose(quat_log(q), [theta * a for a in axis], atol=1e-9)
    np.testing.assert_allclose(quat_log(tuple(-c for c in q)), quat_log(q), atol=1e-9)


@given(angle, st.floats(-1.5, 1.5), angle, angle, st.floats(-1.5, 1.5))
def test_shortest_arc_maps_src_onto_dst(
    r1: float, p1: float, y1: float, r2: float, p2: float
) -> None:
    src = body_z_ned(euler_to_quat(r1, p1, y1))
    dst = body_z_ned(euler_to_quat(r2, p2, 0.0))
    q = shortest_arc(src, dst)
    np.testing.assert_allclose(rotate(q, src), dst, atol=1e-9)
    # Shortest: its axis is perpendicular to both (no twist about either).
    assert abs(float(np.dot(q[1:], src))) < 1e-9
    assert abs(float(np.dot(q[1:], dst))) < 1e-9


def test_shortest_arc_of_opposite_vectors_is_half_a_turn() -> None:
    q = shortest_arc((0.0, 0.0, 1.0), (0.0, 0.0, -1.0))
    assert q[0] == pytest.approx(0.0)
    np.testing.assert_allclose(rotate(q, (0.0, 0.0, 1.0)), (0.0, 0.0, -1.0), atol=1e-12)


def test_normalise_and_canonical() -> None:
    assert normalise_or_none((2.0, 0.0, 0.0, 0.0)) == (1.0, 0.0, 0.0, 0.0)
    assert normalise_or_none((0.0, 0.0, 0.0, 0.0)) is None
    assert normalise_or_none((math.nan, 0.0, 0.0, 1.0)) is None
    assert normalise_or_none((math.inf, 0.0, 0.0, 1.0)) is None
    assert canonical((-1.0, 0.0, 0.0, 0.0)) == (1.0, -0.0, -0.0, -0.0)
