"""The virtual pilot: what it sees of the vehicle and its outer loop.

On an axis a timeline leaves free, roll and pitch are levelled with a P law on
attitude (:func:`level_rates_rad_s`) and yaw is centred.  Throttle always comes
from the virtual pilot (:func:`throttle_command`):

* ``hold``  -- altitude hold, a saturated PD on altitude with ``hover_throttle``
  as feed-forward and tilt compensation;
* ``climb`` -- climb at ``climb_m_s`` (a "punch-out" before a flip);
* ``coast`` -- feed-forward only (what a pilot holds through a flip or roll).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from sitl.pilot.rc import DEFAULT_RATE_FULL_SCALE_DEG_S

__all__ = [
    "GRAVITY_M_S2",
    "PilotParams",
    "PilotView",
    "ThrottleMode",
    "level_rates_rad_s",
    "throttle_command",
]

GRAVITY_M_S2 = 9.80665
ThrottleMode = Literal["hold", "climb", "coast"]


@dataclass(frozen=True)
class PilotView:
    """What the virtual pilot may see of the true vehicle (filled by the simulator).

    Attributes
    ----------
    t_s : float
        Simulation time, s (monotonic within a flight).
    roll_rad, pitch_rad, yaw_rad : float
        ZYX Euler angles of FRD body w.r.t. NED, rad.
    rate_frd_rad_s : tuple of float
        Body rates (p, q, r), rad/s.
    altitude_m : float
        Height above ground, m, up positive.
    climb_rate_m_s : float
        Vertical speed, m/s, up positive.
    hover_throttle : float
        Normalised throttle that roughly hovers the vehicle (a human learns it).
    """

    t_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rate_frd_rad_s: tuple[float, float, float]
    altitude_m: float
    climb_rate_m_s: float
    hover_throttle: float


@dataclass(frozen=True)
class PilotParams:
    """Gains and limits of the virtual pilot.

    Attributes
    ----------
    rate_full_scale_deg_s : tuple of float
        Stick full scale (roll, pitch, yaw), deg/s.
    level_gain_1_s : float
        Attitude P gain k of :func:`level_rates_rad_s`, 1/s.
    level_rate_max_deg_s : float
        Limit of the levelling rate command, deg/s.
    altitude_m : float
        Default altitude-hold target, m above ground.
    altitude_gain_1_s : float
        Altitude P gain to a climb-rate command, 1/s.
    climb_max_m_s, descent_max_m_s : float
        Limits of the commanded climb and descent rate, m/s (both > 0).
    climb_gain_1_s : float
        Climb-rate P gain to a vertical acceleration command, 1/s.
    accel_max_g : float
        Limit of the vertical acceleration command, in g.
    tilt_comp_min_cos : float
        Tilt compensation ``1/(cos roll cos pitch)`` is used down to this cosine
        and blended to ``inverted_throttle_frac`` at 90 deg of tilt and beyond.
    inverted_throttle_frac : float
        Throttle kept when on the side or inverted, fraction of the upright value.
    throttle_min, throttle_max : float
        Throttle clamp, normalised.
    stick_slew_s : float
        Minimum time for a full deflection from centre (500 us) on ch1/2/4, s.
    throttle_slew_s : float
        Minimum time for a full throttle sweep (1000 us), s.
    """

    rate_full_scale_deg_s: tuple[float, float, float] = DEFAULT_RATE_FULL_SCALE_DEG_S
    level_gain_1_s: float = 5.0
    level_rate_max_deg_s: float = 300.0
    altitude_m: float = 10.0
    altitude_gain_1_s: float = 1.2
    climb_max_m_s: float = 4.0
    descent_max_m_s: float = 3.0
    climb_gain_1_s: float = 3.0
    accel_max_g: float = 0.8
    tilt_comp_min_cos: float = 0.7
    inverted_throttle_frac: float = 0.5
    throttle_min: float = 0.05
    throttle_max: float = 1.0
    stick_slew_s: float = 0.08
    throttle_slew_s: float = 0.25


def level_rates_rad_s(
    roll_rad: float,
    pitch_rad: float,
    gain_1_s: float,
    rate_max_rad_s: float,
    *,
    both_axes: bool = True,
) -> tuple[float, float]:
    """Body rates (p, q) that bring the vehicle back to level, a P law on tilt.

    With ``g_b = (-sin(theta), sin(phi) cos(theta), cos(phi) cos(theta))`` the
    gravity direction in FRD body axes, the shortest rotation to level is about
    ``(-g_y, g_x)`` by the tilt angle ``a = atan2(|(g_x, g_y)|, g_z)``:

    ``(p, q) = k * a / sin(a) * (-g_y, g_x)``   (``both_axes=True``)

    which is ``(-k phi, -k theta)`` for small angles and rolls upright when
    inverted.  When another axis is scripted (``both_axes=False``) the
    component ``k * (-g_y, g_x)`` is used without the ``a/sin(a)`` factor, so
    levelling stays small while a flip on the other axis goes through
    inverted.  The result is scaled down to at most ``rate_max`` in norm.

    Parameters
    ----------
    roll_rad, pitch_rad : float
        ZYX Euler roll and pitch, rad.
    gain_1_s : float
        P gain k, 1/s.
    rate_max_rad_s : float
        Limit of the command's norm, rad/s.
    both_axes : bool
        Whether both roll and pitch are being levelled.

    Returns
    -------
    tuple of float
        (p, q) in rad/s, FRD.
    """
    cp = math.cos(pitch_rad)
    gx = -math.sin(pitch_rad)
    gy = math.sin(roll_rad) * cp
    if both_axes:
        gz = math.cos(roll_rad) * cp
        s = math.hypot(gx, gy)
        if s < 1e-6:
            if gz > 0.0:
                return (0.0, 0.0)
            return (rate_max_rad_s, 0.0)  # exactly inverted: roll upright
        scale = gain_1_s * math.atan2(s, gz) / s
    else:
        scale = gain_1_s
    p = -scale * gy
    q = scale * gx
    norm = math.hypot(p, q)
    if norm > rate_max_rad_s:
        k = rate_max_rad_s / norm
        p *= k
        q *= k
    return (p, q)


def throttle_command(
    mode: ThrottleMode,
    *,
    altitude_m: float,
    climb_rate_m_s: float,
    target_altitude_m: float,
    climb_target_m_s: float,
    hover_throttle: float,
    cos_tilt: float,
    params: PilotParams,
) -> float:
    """Normalised throttle of the virtual pilot's altitude loop.

    ``v_cmd = clamp(k_z (z_ref - z), -v_down, v_up)`` (``hold``) or
    ``climb_m_s`` (``climb``); ``a_cmd = clamp(k_v (v_cmd - v), +-a_max)``
    (0 in ``coast``); then

    ``T = clamp(T_hover (1 + a_cmd / g) f(c), T_min, T_max)``

    where ``c = cos(roll) cos(pitch)`` and ``f(c) = 1/c`` when nearly upright
    (``c >= tilt_comp_min_cos``), blending linearly to ``inverted_throttle_frac``
    at ``c = 0`` and constant beyond (on the side or inverted).

    Parameters
    ----------
    mode : {"hold", "climb", "coast"}
        Throttle mode.
    altitude_m, climb_rate_m_s : float
        Measured height above ground (m) and vertical speed (m/s), up positive.
    target_altitude_m : float
        Hold target, m.
    climb_target_m_s : float
        Climb-rate target in ``climb`` mode, m/s.
    hover_throttle : float
        Feed-forward, normalised.
    cos_tilt : float
        ``cos(roll) cos(pitch)``.
    params : PilotParams
        Gains and limits.

    Returns
    -------
    float
        Throttle in ``[throttle_min, throttle_max]``.
    """
    if mode == "coast":
        accel = 0.0
    else:
        if mode == "hold":
            v_cmd = params.altitude_gain_1_s * (target_altitude_m - altitude_m)
            v_cmd = min(max(v_cmd, -params.descent_max_m_s), params.climb_max_m_s)
        else:
            v_cmd = climb_target_m_s
        a_max = params.accel_max_g * GRAVITY_M_S2
        accel = min(max(params.climb_gain_1_s * (v_cmd - climb_rate_m_s), -a_max), a_max)
    c_min = params.tilt_comp_min_cos
    if cos_tilt >= c_min:
        factor = 1.0 / cos_tilt
    elif cos_tilt > 0.0:
        frac = cos_tilt / c_min
        factor = params.inverted_throttle_frac + frac * (
            1.0 / c_min - params.inverted_throttle_frac
        )
    else:
        factor = params.inverted_throttle_frac
    thr = hover_throttle * (1.0 + accel / GRAVITY_M_S2) * factor
    return min(max(thr, params.throttle_min), params.throttle_max)
