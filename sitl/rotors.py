"""The motors and rotors: commanded speed, motor lag, rotor forces and torques.

Commands are normalised, clamped to ``[0, 1]`` (non-finite reads as 0). A
command of exactly 0 means "stopped" (disarmed): ``w_cmd = 0``. Any positive
command maps linearly onto speed,
``w_cmd = w_idle + cmd (w_max - w_idle)``, so thrust is quadratic in the command
as on a real ESC. Rotor speed follows a first-order lag with ``tau_up`` when
speeding up and ``tau_down`` when slowing down. With the command held over a step
this ODE is solved exactly, ``w(s) = w_cmd + (w_0 - w_cmd) e^{-s/tau}`` (it never
crosses ``w_cmd``, so the choice of tau is fixed within a step), as is the phase
integral.

Rotor imbalance (a cut or damaged prop) is a radial force rotating with the
rotor at its position: ``F_imb,i = A_i (w_i / w_max)^2 (cos phi_i, sin phi_i, 0)``
with ``dphi_i/dt = -sigma_i w_i`` (a CCW rotor turns from +y towards +x in FRD).
It excites the airframe at the rotor frequency ``w_i / 2pi``: through the yaw arm
and, when the rotor plane is above or below the CG, in roll and pitch.

Damage: after ``fail_at_s`` a motor delivers ``efficiency_after_fail`` of its
thrust and torque, modelled as a loss of motor power: its commanded speed is
scaled by ``sqrt(efficiency_after_fail)`` (0: the rotor spins down and stops).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from companion.profile import VehicleProfile
from sitl.vehicle_params import GRAVITY_M_S2, VehicleParams

__all__ = ["Rotors", "hover_motor_command", "motor_command_to_speed"]

_log = logging.getLogger(__name__)

_TWO_PI = 2.0 * math.pi


def motor_command_to_speed(cmd: float, w_idle_rad_s: float, w_max_rad_s: float) -> float:
    """Commanded rotor speed (rad/s) for a normalised command.

    ``0`` (or below, or non-finite) -> 0 (stopped); ``cmd in (0, 1]`` ->
    ``w_idle + cmd (w_max - w_idle)``; above 1 is clamped to ``w_max``.
    """
    if not 0.0 < cmd < math.inf:  # also catches NaN
        return 0.0
    if cmd >= 1.0:
        return w_max_rad_s
    return w_idle_rad_s + cmd * (w_max_rad_s - w_idle_rad_s)


def hover_motor_command(profile: VehicleProfile, *, include_damage: bool = True) -> float:
    """Equal motor command whose total steady thrust equals the weight.

    ``sum_i k_T,i w^2 = m g``  ->  ``w = sqrt(m g / sum_i k_T,i)``,
    ``cmd = (w - w_idle) / (w_max - w_idle)``.

    With ``include_damage`` the per-motor thrust efficiencies are used (failures
    are not). Equal commands balance torques only for a symmetric, undamaged
    vehicle with the CG at the centre.

    Raises
    ------
    ValueError
        If that speed is outside ``[w_idle, w_max]`` (cannot hover on equal commands).
    """
    ph = profile.physics
    if include_damage:
        kt_sum = sum(VehicleParams.from_profile(profile).thrust_coeff)
    else:
        kt_sum = profile.n_motors * ph.kf_n_per_rad_s2
    w = math.sqrt(ph.mass_kg * GRAVITY_M_S2 / kt_sum)
    w_idle, w_max = ph.motor_w_idle_rad_s, ph.motor_w_max_rad_s
    if not w_idle <= w <= w_max:
        raise ValueError(f"hover speed {w:.1f} rad/s outside [{w_idle}, {w_max}] rad/s")
    return (w - w_idle) / (w_max - w_idle)


class Rotors:
    """The rotors of one vehicle, stepped at a fixed ``dt_s``.

    Holds the rotor speeds, phases and failures. :meth:`advance` moves them
    over one step and returns the rotor wrench at its start, middle and end.

    Parameters
    ----------
    params : VehicleParams
        The vehicle's constants.
    dt_s : float
        Step (s).
    rng : numpy.random.Generator
        Draws the initial rotor phases (where imbalanced props start).

    Attributes
    ----------
    speed_rad_s : list of float
        Rotor speeds (rad/s), in motor output order; all stopped at first.
    phase_rad : list of float
        Rotor angles (rad) that orient each imbalance force in the rotor plane.
    """

    def __init__(self, params: VehicleParams, dt_s: float, rng: np.random.Generator) -> None:
        P = params
        n = P.n_motors
        self.params = P
        self.dt_s = dt_s
        self._n = n
        # Per-motor linear coefficients of the wrench in w^2 and in w:
        # (Fz, tau_x, tau_y, tau_z) per unit w^2, and sigma * J_r for the rotor terms.
        self._coef_w2 = tuple(
            (
                -P.thrust_coeff[i],
                -P.arm_frd_m[i][1] * P.thrust_coeff[i],
                P.arm_frd_m[i][0] * P.thrust_coeff[i],
                P.spin_sign[i] * P.torque_coeff[i],
            )
            for i in range(n)
        )
        self._sigma_jr = tuple(s * P.rotor_inertia_kg_m2 for s in P.spin_sign)
        self._has_imbalance = any(a > 0.0 for a in P.imbalance_coeff)
        h = 0.5 * dt_s
        self._exp_up = (math.exp(-h / P.tau_up_s), math.exp(-dt_s / P.tau_up_s))
        self._exp_down = (math.exp(-h / P.tau_down_s), math.exp(-dt_s / P.tau_down_s))
        self._speed_scale = [1.0] * n
        self._failed = [False] * n
        # Where each imbalanced prop starts: the plant's only randomness.
        self.phase_rad = [float(v) for v in rng.uniform(0.0, _TWO_PI, size=n)]
        self.speed_rad_s = [0.0] * n

    def fail(self, motor: int, efficiency: float = 0.0) -> None:
        """Degrade ``motor`` now to ``efficiency`` of its thrust and torque.

        Same model as ``damage.motors[].fail_at_s``: commanded speed scaled by
        ``sqrt(efficiency)``.
        """
        if not 0 <= motor < self._n:
            raise ValueError(f"motor: expected 0..{self._n - 1}, got {motor}")
        if not 0.0 <= efficiency <= 1.0:
            raise ValueError(f"efficiency: expected in [0, 1], got {efficiency}")
        self._failed[motor] = True
        self._speed_scale[motor] = math.sqrt(efficiency)

    def targets(self, motor_cmd: Sequence[float], t_s: float) -> list[float]:
        """Commanded rotor speeds at time ``t_s``, failures applied (see module docs)."""
        P = self.params
        n = self._n
        if len(motor_cmd) != n:
            raise ValueError(f"motor_cmd: expected {n} commands, got {len(motor_cmd)}")
        for i, t_fail in enumerate(P.fail_at_s):
            if t_fail is not None and not self._failed[i] and t_s >= t_fail - 1e-9:
                self._failed[i] = True
                self._speed_scale[i] = P.speed_scale_after_fail[i]
                _log.info("motor %d degraded at t=%.3f s", i, t_s)
        w_idle, w_max = P.w_idle_rad_s, P.w_max_rad_s
        scale = self._speed_scale
        out = [0.0] * n
        for i in range(n):
            c = motor_cmd[i]
            if 0.0 < c < math.inf:  # NaN, inf and negatives stay stopped
                w = w_max if c >= 1.0 else w_idle + c * (w_max - w_idle)
                out[i] = w * scale[i]
        return out

    def advance(
        self, w_cmd: list[float]
    ) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        """Exact motor lag over one step; the rotor wrench at ``s = 0, dt/2, dt``.

        Updates rotor speeds and phases to the end of the step.
        """
        P = self.params
        dt = self.dt_s
        w = self.speed_rad_s
        coef = self._coef_w2
        sjr = self._sigma_jr
        fz0 = tx0 = ty0 = tz0 = hz0 = 0.0
        fz1 = tx1 = ty1 = tz1 = hz1 = 0.0
        fz2 = tx2 = ty2 = tz2 = hz2 = 0.0
        w_mid = [0.0] * self._n
        w_end = [0.0] * self._n
        taus = [0.0] * self._n
        for i in range(self._n):
            w0 = w[i]
            wc = w_cmd[i]
            if wc >= w0:
                tau = P.tau_up_s
                eh, ef = self._exp_up
            else:
                tau = P.tau_down_s
                eh, ef = self._exp_down
            taus[i] = tau
            d = w0 - wc
            wh = wc + d * eh
            wf = wc + d * ef
            w_mid[i] = wh
            w_end[i] = wf
            a_f, a_x, a_y, a_z = coef[i]
            s = sjr[i]  # sigma J_r
            # Rotor speed-up reaction on the frame: +sigma J_r dw/dt about z,
            # dw/dt = (w_cmd - w) / tau; rotor momentum h_z = -sigma J_r w.
            inv_tau = s / tau
            w2 = w0 * w0
            fz0 += a_f * w2
            tx0 += a_x * w2
            ty0 += a_y * w2
            tz0 += a_z * w2 - inv_tau * d
            hz0 -= s * w0
            w2 = wh * wh
            fz1 += a_f * w2
            tx1 += a_x * w2
            ty1 += a_y * w2
            tz1 += a_z * w2 - inv_tau * (wh - wc)
            hz1 -= s * wh
            w2 = wf * wf
            fz2 += a_f * w2
            tx2 += a_x * w2
            ty2 += a_y * w2
            tz2 += a_z * w2 - inv_tau * (wf - wc)
            hz2 -= s * wf
        fx0 = fy0 = fx1 = fy1 = fx2 = fy2 = 0.0
        if self._has_imbalance:
            h = 0.5 * dt
            for i in range(self._n):
                a = P.imbalance_coeff[i]
                if a <= 0.0:
                    continue
                rx, ry, rz = P.arm_frd_m[i]
                sgn = P.spin_sign[i]
                tau = taus[i]
                w0, wc = w[i], w_cmd[i]
                d = w0 - wc
                ph0 = self.phase_rad[i]
                # Phase = phase0 - sigma * integral of w(s) ds, integrated exactly.
                ph1 = ph0 - sgn * (wc * h + tau * (d - (w_mid[i] - wc)))
                ph2 = ph0 - sgn * (wc * dt + tau * (d - (w_end[i] - wc)))
                self.phase_rad[i] = math.fmod(ph2, _TWO_PI)
                for k, (wk, ph) in enumerate(((w0, ph0), (w_mid[i], ph1), (w_end[i], ph2))):
                    amp = a * wk * wk
                    Fx = amp * math.cos(ph)
                    Fy = amp * math.sin(ph)
                    # r x F for F in the rotor plane.
                    dtx, dty, dtz = -rz * Fy, rz * Fx, rx * Fy - ry * Fx
                    if k == 0:
                        fx0 += Fx
                        fy0 += Fy
                        tx0 += dtx
                        ty0 += dty
                        tz0 += dtz
                    elif k == 1:
                        fx1 += Fx
                        fy1 += Fy
                        tx1 += dtx
                        ty1 += dty
                        tz1 += dtz
                    else:
                        fx2 += Fx
                        fy2 += Fy
                        tx2 += dtx
                        ty2 += dty
                        tz2 += dtz
        self.speed_rad_s = w_end
        return (
            (fx0, fy0, fz0, tx0, ty0, tz0, hz0),
            (fx1, fy1, fz1, tx1, ty1, tz1, hz1),
            (fx2, fy2, fz2, tx2, ty2, tz2, hz2),
        )
