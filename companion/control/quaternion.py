r"""Quaternions for the attitude loop: small pure functions on plain float tuples.

Conventions (PX4, MAVLink ``ATTITUDE_QUATERNION``):

* World frame NED (x north, y east, z down), body frame FRD (x forward, y right,
  z down). Positive roll = right side down, positive pitch = nose up, positive
  yaw = nose right.
* Quaternions are scalar-first, ``q_wxyz = (w, x, y, z)``, and rotate body
  vectors into the world: :math:`v_{ned} = q \otimes (0, v_{frd}) \otimes q^*`,
  :math:`v_{ned} = R(q)\, v_{frd}`.
* Euler angles are the aerospace ZYX sequence: yaw :math:`\psi` about z, then
  pitch :math:`\theta` about the new y, then roll :math:`\phi` about the new x.

``sitl.frames`` has the same conventions; the product may not import ``sitl``, so
the few functions the attitude loop needs live here (no numpy: per-sample code).
"""

from __future__ import annotations

import math

__all__ = [
    "Quat",
    "Vec3",
    "body_z_ned",
    "canonical",
    "euler_to_quat",
    "ned_down_frd",
    "normalise_or_none",
    "quat_conj",
    "quat_log",
    "quat_mul",
    "shortest_arc",
    "yaw_rad",
]

Quat = tuple[float, float, float, float]
Vec3 = tuple[float, float, float]


def quat_mul(a: Quat, b: Quat) -> Quat:
    """Hamilton product ``a ⊗ b``: the rotation ``b`` followed by ``a`` (in the
    frame ``a`` maps from: ``q_world_body ⊗ q_body_other``)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_conj(q: Quat) -> Quat:
    """Conjugate ``(w, -x, -y, -z)``: the inverse rotation of a unit quaternion."""
    return (q[0], -q[1], -q[2], -q[3])


def canonical(q: Quat) -> Quat:
    """``q`` or ``-q``, whichever has ``w >= 0``: the same rotation, by the short way
    (a rotation angle in [0, pi])."""
    if q[0] < 0.0:
        return (-q[0], -q[1], -q[2], -q[3])
    return q


def normalise_or_none(q: Quat) -> Quat | None:
    """``q`` scaled to unit norm, or ``None`` if its norm is zero or not finite
    (no rotation can be recovered; the caller decides what to fly instead)."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not (n > 1e-6 and math.isfinite(n)):
        return None
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def euler_to_quat(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Quat:
    """Unit quaternion of the ZYX sequence: ``q = q_z(yaw) ⊗ q_y(pitch) ⊗ q_x(roll)``."""
    cr, sr = math.cos(0.5 * roll_rad), math.sin(0.5 * roll_rad)
    cp, sp = math.cos(0.5 * pitch_rad), math.sin(0.5 * pitch_rad)
    cy, sy = math.cos(0.5 * yaw_rad), math.sin(0.5 * yaw_rad)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def yaw_rad(q: Quat) -> float:
    r"""ZYX yaw (heading) of a unit quaternion, rad in [-pi, pi]:
    :math:`\psi = \operatorname{atan2}(2(wz + xy),\, 1 - 2(y^2 + z^2))`."""
    w, x, y, z = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def body_z_ned(q: Quat) -> Vec3:
    """The body z axis (FRD "down", the thrust's opposite) in NED: the third column
    of ``R(q)``. Its z component is ``cos(tilt)``."""
    w, x, y, z = q
    return (2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y))


def ned_down_frd(q: Quat) -> Vec3:
    """The NED down axis in the body (FRD): the third row of ``R(q)``. A yaw rate
    about the world vertical is this vector times the rate in body axes."""
    w, x, y, z = q
    return (2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))


def shortest_arc(src: Vec3, dst: Vec3) -> Quat:
    r"""The smallest rotation taking unit vector ``src`` onto unit vector ``dst``.

    The half-way construction: :math:`q \propto (1 + s \cdot d,\; s \times d)`,
    normalised. For opposite vectors (no unique axis) the rotation is by pi about
    an axis perpendicular to ``src`` (the one PX4's ``Quaternion(src, dst)``
    picks: ``src`` crossed with the basis axis least aligned with it).
    """
    sx, sy, sz = src
    dx, dy, dz = dst
    cx = sy * dz - sz * dy
    cy = sz * dx - sx * dz
    cz = sx * dy - sy * dx
    dot = sx * dx + sy * dy + sz * dz
    if cx * cx + cy * cy + cz * cz < 1e-10 and dot < 0.0:
        ax, ay, az = abs(sx), abs(sy), abs(sz)
        if ax < ay:
            b = (1.0, 0.0, 0.0) if ax < az else (0.0, 0.0, 1.0)
        else:
            b = (0.0, 1.0, 0.0) if ay < az else (0.0, 0.0, 1.0)
        cx = sy * b[2] - sz * b[1]
        cy = sz * b[0] - sx * b[2]
        cz = sx * b[1] - sy * b[0]
        w = 0.0
    else:
        w = dot + math.sqrt((sx * sx + sy * sy + sz * sz) * (dx * dx + dy * dy + dz * dz))
    n = math.sqrt(w * w + cx * cx + cy * cy + cz * cz)
    return (w / n, cx / n, cy / n, cz / n)


def quat_log(q: Quat) -> Vec3:
    r"""Rotation vector of a unit quaternion, by the short way: the axis times the
    angle in [0, pi], rad.

    With ``q`` canonical (:math:`w \ge 0`) and :math:`n = |(x, y, z)|`, the angle is
    :math:`\theta = 2 \operatorname{atan2}(n, w)` and the vector is
    :math:`\theta (x, y, z) / n`; for a tiny ``n`` the limit :math:`2 (x, y, z) / w`.
    Unlike ``2 (x, y, z)`` (PX4's ``sin(theta/2)``-scaled error), its magnitude is
    the angle itself, so a rotation about one axis at rate ``omega`` moves it at
    exactly ``omega``.
    """
    w, x, y, z = canonical(q)
    n = math.sqrt(x * x + y * y + z * z)
    k = 2.0 * math.atan2(n, w) / n if n > 1e-9 else 2.0 / w
    return (k * x, k * y, k * z)
