"""Frames and quaternions: small pure functions on plain tuples.

Conventions (PX4, MAVLink):

* World frame NED (x north, y east, z down); body frame FRD (x forward, y right,
  z down). Positive roll ``p`` = right wing down, positive pitch ``q`` = nose up,
  positive yaw ``r`` = nose right.
* Quaternions are scalar-first ``q_wxyz = (w, x, y, z)`` (MAVLink order; RotorPy
  and SciPy use ``(x, y, z, w)``, see :func:`q_wxyz_to_xyzw`). A quaternion ``q``
  rotates body vectors into the world: ``v_ned = q ⊗ (0, v_frd) ⊗ q*``.
* Euler angles are the aerospace ZYX sequence: yaw ``psi`` about z, then pitch
  ``theta`` about the new y, then roll ``phi`` about the new x.

Everything here takes and returns tuples of Python floats: these functions sit in
per-step code where a small numpy array costs more than the arithmetic.
"""

from __future__ import annotations

import math

__all__ = [
    "Quat",
    "Vec3",
    "axis_angle_to_quat",
    "euler_to_quat",
    "frd_to_flu",
    "ned_to_enu",
    "normalise",
    "q_wxyz_to_xyzw",
    "q_xyzw_to_wxyz",
    "quat_conj",
    "quat_mul",
    "quat_rotate",
    "quat_rotate_inv",
    "quat_to_axis_angle",
    "quat_to_dcm",
    "quat_to_euler_rad",
    "tilt_rad",
]

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


def quat_mul(a: Quat, b: Quat) -> Quat:
    """Hamilton product ``a ⊗ b`` (``b`` applied first, then ``a``).

    With ``a`` = world<-body and ``b`` = body<-other the product is world<-other.
    """
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    w = w1 * w2 - (x1 * x2 + y1 * y2 + z1 * z2)
    x = w1 * x2 + w2 * x1 + (y1 * z2 - z1 * y2)
    y = w1 * y2 + w2 * y1 + (z1 * x2 - x1 * z2)
    z = w1 * z2 + w2 * z1 + (x1 * y2 - y1 * x2)
    return (w, x, y, z)


def quat_conj(q: Quat) -> Quat:
    """The inverse rotation of a unit quaternion: its vector part negated."""
    w, x, y, z = q
    return (w, -x, -y, -z)


def euler_to_quat(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Quat:
    """ZYX Euler angles to a unit quaternion: yaw about z, then pitch, then roll.

    Built as the product of the three elementary rotations,
    ``q = q_z(yaw) ⊗ q_y(pitch) ⊗ q_x(roll)``.
    """
    h = 0.5
    qz = (math.cos(h * yaw_rad), 0.0, 0.0, math.sin(h * yaw_rad))
    qy = (math.cos(h * pitch_rad), 0.0, math.sin(h * pitch_rad), 0.0)
    qx = (math.cos(h * roll_rad), math.sin(h * roll_rad), 0.0, 0.0)
    return quat_mul(quat_mul(qz, qy), qx)


def axis_angle_to_quat(rotation_vector: Vec3) -> Quat:
    """Quaternion of a rotation vector (axis times angle, rad); identity for zero."""
    rx, ry, rz = rotation_vector
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-12:
        return (1.0, 0.0, 0.0, 0.0)
    s = math.sin(0.5 * angle) / angle
    return (math.cos(0.5 * angle), rx * s, ry * s, rz * s)


def quat_to_axis_angle(q: Quat) -> Vec3:
    """Rotation vector (axis times angle, rad, angle in [0, pi]) of a unit quaternion."""
    w, x, y, z = q
    if w < 0.0:  # the same rotation the short way round
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-12:
        return (0.0, 0.0, 0.0)
    angle = 2.0 * math.atan2(s, w)
    k = angle / s
    return (x * k, y * k, z * k)


def normalise(q: Quat) -> Quat:
    """Scale ``q`` to unit norm.

    Raises
    ------
    ValueError
        If ``q`` has zero or non-finite norm (no rotation can be recovered).
    """
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not (n > 0.0 and math.isfinite(n)):
        raise ValueError(f"cannot normalise quaternion {q!r}")
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def quat_to_dcm(q: Quat) -> tuple[Vec3, Vec3, Vec3]:
    """Rotation matrix ``R`` (rows) with ``v_ned = R v_frd`` for a unit ``q``.

    ``R = [[1-2(y²+z²), 2(xy-wz), 2(xz+wy)],
           [2(xy+wz), 1-2(x²+z²), 2(yz-wx)],
           [2(xz-wy), 2(yz+wx), 1-2(x²+y²)]]``
    """
    w, x, y, z = q
    return (
        (1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)),
        (2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)),
        (2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)),
    )


def quat_rotate(q: Quat, v: Vec3) -> Vec3:
    """Rotate a body (FRD) vector into the world (NED): ``R(q) v``."""
    R = quat_to_dcm(q)
    return (
        R[0][0] * v[0] + R[0][1] * v[1] + R[0][2] * v[2],
        R[1][0] * v[0] + R[1][1] * v[1] + R[1][2] * v[2],
        R[2][0] * v[0] + R[2][1] * v[1] + R[2][2] * v[2],
    )


def quat_rotate_inv(q: Quat, v: Vec3) -> Vec3:
    """Rotate a world (NED) vector into the body (FRD): ``R(q)ᵀ v``."""
    R = quat_to_dcm(q)
    return (
        R[0][0] * v[0] + R[1][0] * v[1] + R[2][0] * v[2],
        R[0][1] * v[0] + R[1][1] * v[1] + R[2][1] * v[2],
        R[0][2] * v[0] + R[1][2] * v[1] + R[2][2] * v[2],
    )


def quat_to_euler_rad(q: Quat) -> Vec3:
    """ZYX Euler angles ``(roll, pitch, yaw)`` in radians of a unit quaternion.

    ``roll = atan2(2(wx+yz), 1-2(x²+y²))``, ``pitch = asin(2(wy-xz))`` (clamped at
    ±pi/2 so rounding near gimbal lock cannot produce NaN),
    ``yaw = atan2(2(wz+xy), 1-2(y²+z²))``.
    """
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    s = 2.0 * (w * y - x * z)
    pitch = math.asin(max(-1.0, min(1.0, s)))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return (roll, pitch, yaw)


def tilt_rad(q: Quat) -> float:
    """Angle between body z and world z (0 = level, pi = upside down).

    ``cos(tilt) = R[2][2] = 1 - 2(x² + y²)``.
    """
    c = 1.0 - 2.0 * (q[1] * q[1] + q[2] * q[2])
    return math.acos(max(-1.0, min(1.0, c)))


def ned_to_enu(v_ned: Vec3) -> Vec3:
    """NED vector to ENU (ROS/Gazebo world): swap x and y, negate z."""
    return (v_ned[1], v_ned[0], -v_ned[2])


def frd_to_flu(v_frd: Vec3) -> Vec3:
    """FRD body vector to FLU (ROS body): negate y and z. Its own inverse."""
    return (v_frd[0], -v_frd[1], -v_frd[2])


def q_wxyz_to_xyzw(q: Quat) -> Quat:
    """Scalar-first (MAVLink) to scalar-last (RotorPy, SciPy) order."""
    return (q[1], q[2], q[3], q[0])


def q_xyzw_to_wxyz(q: Quat) -> Quat:
    """Scalar-last (RotorPy, SciPy) to scalar-first (MAVLink) order."""
    return (q[3], q[0], q[1], q[2])
