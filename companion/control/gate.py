"""The last gate: every command leaving the companion passes here.

The laws and the mixer already saturate their outputs, and the app rejects
non-finite measurements before the law sees them; this gate is the one check
that does not depend on any of that being right. A value outside its range
is clamped to the range; a value that is not a number (NaN, which every
ordered comparison calls false, so ``max(-m, min(m, x))`` turns it into
``+m``) becomes the safe value of its field:

======================  =================  ==================================
output                  field              safe value
======================  =================  ==================================
actuator (torques)      roll, pitch, yaw   0 (no torque)
actuator                thrust             ``safe_thrust`` (the pilot's collective)
rates                   roll, pitch, yaw   the pilot's rate (else 0)
rates                   thrust             ``safe_thrust`` (the last thrust sent)
======================  =================  ==================================

A safe value that is itself NaN becomes 0 (within the range). Infinities are
numbers beyond the range: they clamp. Each function returns the gated values
and how many fields it had to replace (clamps of finite values are not
counted: the laws' own saturation produces them all the time).
"""

from __future__ import annotations

__all__ = ["gate_actuator", "gate_rates"]


def _clamp(x: float, lo: float, hi: float, safe: float) -> float:
    """``x`` within ``[lo, hi]``; ``safe`` (itself clamped, 0-safe) if ``x`` is NaN."""
    if lo <= x <= hi:
        return x
    if x > hi:
        return hi
    if x < lo:
        return lo
    # NaN: the safe value, itself inside the range (or the range's nearest end).
    if lo <= safe <= hi:
        return safe
    return hi if safe > hi else lo if safe < lo else min(max(0.0, lo), hi)


def gate_actuator(
    torque: tuple[float, float, float], thrust: float, safe_thrust: float
) -> tuple[tuple[float, float, float, float], int]:
    """Roll, pitch, yaw torque in [-1, 1] and thrust in [0, 1], NaN replaced.

    Returns
    -------
    controls, replaced
        ``(roll, pitch, yaw, thrust)`` ready for ``SET_ACTUATOR_CONTROL_TARGET``,
        and the number of fields that were NaN.
    """
    r, p, y = torque
    replaced = (r != r) + (p != p) + (y != y) + (thrust != thrust)
    return (
        _clamp(r, -1.0, 1.0, 0.0),
        _clamp(p, -1.0, 1.0, 0.0),
        _clamp(y, -1.0, 1.0, 0.0),
        _clamp(thrust, 0.0, 1.0, safe_thrust),
    ), replaced


def gate_rates(
    rates: tuple[float, float, float] | list[float],
    thrust: float,
    pilot_rates: tuple[float, float, float],
    rate_max: tuple[float, float, float],
    safe_thrust: float,
) -> tuple[tuple[float, float, float], float, int]:
    """Body rates within ``+-rate_max`` (rad/s) and thrust in [0, 1], NaN replaced.

    A NaN rate becomes the pilot's rate for that axis (the autopilot's own
    rate loop then flies what the pilot asked); a NaN thrust becomes ``safe_thrust``.

    Returns
    -------
    rates, thrust, replaced
    """
    r, p, y = rates
    replaced = (r != r) + (p != p) + (y != y) + (thrust != thrust)
    m0, m1, m2 = rate_max
    s0, s1, s2 = pilot_rates
    return (
        (_clamp(r, -m0, m0, s0), _clamp(p, -m1, m1, s1), _clamp(y, -m2, m2, s2)),
        _clamp(thrust, 0.0, 1.0, safe_thrust),
        replaced,
    )
