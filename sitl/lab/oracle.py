r"""The oracle: a rate controller that knows the plant, flown in the lab's simulation.

A reference for every tracking figure: for a scenario and a vehicle, what a
controller that knows the true plant and sees its true state reaches under the
same actuator limits, motor lag, mixer and sensor path as the shipped laws. It is
flown by :func:`sitl.lab.simulate.simulate_flight` like any law (same pilot, same
sticks, same link, same metrics, measured against the gyro as the flights are);
it is a *reference, not a bound*: see "What it is not" below.

What it knows
-------------
The vehicle profile's physics as :mod:`sitl.rotors` and :mod:`sitl.physics` use
them (:class:`sitl.vehicle_params.VehicleParams`: inertia about the CG, arms about
the CG, per-motor thrust and drag-torque coefficients with damage folded in,
failures, the motor map and its time constants up and down, rotor inertia,
angular drag), and at each IMU sample the plant's true state (body rates, rotor
speeds and phases, attitude, altitude), read from the simulator through the
loop's ``see_plant`` hook. It does not know the pilot's next stick move.

The law, per IMU sample (held until the next, ``h`` = the IMU period)
-------------------------------------------------------------------------
Let ``L = J omega + h_r`` be the angular momentum (rotors included,
``h_r = -J_r sum_i sigma_i w_i e_z``), ``tau(w)`` the rotor thrust and drag
torques and ``b = J^{-1}(omega x L + D omega)``, so that the body's angular
acceleration is ``a = J^{-1} tau(w) - b`` plus, about z, the rotors' spin-up
reaction. The rotating imbalance of a damaged prop (its part of ``omega``,
``J^{-1} sigma_i a_i w_i (-z_i cos phi_i, -z_i sin phi_i, x_i cos phi_i + y_i
sin phi_i)``, from the known rotor phases) is taken out of the rate it controls:
no law can cancel a disturbance at the rotor frequency through motors this slow,
and chasing it would only shake the motors.

Each motor's speed over the interval is known exactly for a given command
(first-order lag, ``tau_up`` or ``tau_down`` by direction, as :mod:`sitl.rotors`
solves it), so the oracle predicts the rates at the end of the interval,
``omega_h = J^{-1}(L + h (mean tau(w) - omega x L - D omega) - h_r(w_h))``
(spin-up reaction included through ``h_r``), and the angular acceleration there,
``a_h``, for any command. It picks the command by what those predictions miss:

* **Roll and pitch** (relative degree two: command -> rotor speed -> torque ->
  rate): the offline ideal tracker's law (``ideal_tracker_rates`` of
  ``scripts/reproduce_paper.py``) on the real plant: the point where the rate
  would stop, braking at full opposite command from the end of the interval,
  :math:`\omega_h + \tau (a_h - A \ln(1 + a_h / A))`, on the reference (``A`` the
  opposite full-command acceleration, :func:`sitl.envelope.angular_accel_limits_rad_s2`
  net of ``b``; ``tau`` the mean of the two motor time constants). Time-optimal
  for a first-order lag on the acceleration: bang-bang onto the new rate. Near
  zero acceleration the braking term is kept at least ``KAPPA tau a_h`` so the
  law does not chatter from full to full command on the small errors the real,
  coupled plant leaves (the ideal tracker's plant leaves none).
* **Yaw** (relative degree one: the rotors' spin-up reaction moves the rate within
  a motor time constant, ``J_z r = L_z + J_r s`` with ``s = sum_i sigma_i w_i``):
  dead-beat on the rate, ``r_h`` on the reference. Holding ``r`` afterwards is
  always feasible when ``T = J_r / (dQ/ds)`` exceeds the motor lag (the drag
  torque ``Q`` moves ``L_z`` slower than the reaction can answer):
  :meth:`OracleController.yaw_reaction_ratio` is 5.7-12.5 on the bundled
  vehicles and 2.6-33 on the envelope's corners and their damage variants.
* **Through the product's mixer** (:func:`companion.config.build_mixer`: the same
  air-mode priority, clamps and idle): Newton steps on the normalised roll, pitch
  and yaw requests in the mixer's own order, roll and pitch together, then yaw
  with what they leave, each judged on the motor commands the mixer really
  makes, with the motor map, the damage and the failures; the mixer then says
  what it realised and saturated, as for the shipped laws (an axis also counts
  as saturated when the law wanted more than it sent). When roll and pitch
  together want more than the motors' spread, the axis further from its
  reference gets its request first (the mixer would scale both down, and a small
  correction on one axis would cost the other's flip half its authority). Yaw
  gets what roll and pitch leave, as it does behind this mixer for any law
  (``yaw_reserve`` keeps a share of the range from roll and pitch while the yaw
  error is large, and their braking then counts on the rest: it trades roll and
  pitch for yaw, off by default).
* **Collective**: the pilot's, as for the shipped laws; with ``collective=True``
  (the feasibility judge, :func:`collective_command`) the oracle sets it too: no
  thrust when the thrust points down, at least the pilot's when it points up, and
  full thrust once the vehicle, sinking, is within its braking distance of the
  ground (half the upright thrust margin as deceleration, 1 m above it). The
  mixer keeps roll and pitch first.

Measured (full ``paper-acro``, MAE against the filtered gyro, roll / pitch): F450
5.9 / 5.5 against the offline ideal tracker's 5.6 / 5.3 on the same reference
(+6 % / +5 %); cut props 10.2 / 8.8 against 9.4 / 8.2 (the rotating imbalance
the ideal tracker does not have); Tarot 11.5 / 7.2 against 10.3 / 6.3 and x500
5.5 / 4.7 against 4.8 / 4.1 (their motors spin down slower than up; the ideal
tracker takes the faster). Below the shipped MFC on roll and pitch on every
paper vehicle; above it on the measured yaw (see "What it is not").

What it is not
--------------
Not a bound: a controller with a preview of the sticks, one that leads the gyro
filter (the oracle tracks the true rate; the figure is read, as the flights' are,
from the filtered gyro, so a law that closes its loop on the filtered gyro, as
MFC does, can score better there while tracking the true rate worse), one that
shares the motors between the axes by their errors instead of by the mixer's
fixed priority, one that plans over more than one sample against the coupled,
saturating plant, or a luckier one, can do better. The braking model is first
order on the acceleration with one time constant and fixed full-command limits
per axis (roll and pitch share the mixer's spread); wind acts only through the
angular drag and the gyroscopic terms it sees. It does not compensate a
companion link's delay (it sees the plant at the sample's arrival and its
command waits in the downlink like any).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.config import MfcConfig, PidConfig, build_mixer
from companion.control.mfc import ControlOutput
from companion.control.yaw_share import YawShare
from companion.profile import VehicleProfile
from sitl.link_model import LinkSpec
from sitl.scenario import Scenario
from sitl.vehicle_params import GRAVITY_M_S2, VehicleParams

if TYPE_CHECKING:
    from sitl.lab.simulate import FlightRecord

__all__ = [
    "COLLECTIVE_BRAKE_FRACTION",
    "COLLECTIVE_MARGIN_M",
    "KAPPA",
    "YAW_RESERVE",
    "OracleController",
    "collective_command",
    "fly_oracle",
    "oracle_flight",
]

_ZERO3 = (0.0, 0.0, 0.0)
_NO_CUT = (False, False, False)
_NEWTON_STEPS = 3

KAPPA = 0.2
"""Least share of the acceleration's lag the stopping point counts (``_stop_term``).
0 is the ideal tracker's pure time-optimal law, which on the coupled plant chatters
from full to full command on small errors and starves yaw behind the mixer; 0.2
keeps roll and pitch within about 5 % of the ideal tracker on the F450 (0.1: 5 % /
4 %, 0.3: 10 % / 7 %) and gives yaw most of what a smoother law would."""

YAW_RESERVE = 0.0
"""Share of the motor range kept from roll and pitch for yaw while its error is large
(scaled by the yaw error up to :data:`YAW_RESERVE_ERROR_RAD_S`). 0: the mixer's own
priority, roll and pitch first, as for every law behind this mixer."""

YAW_RESERVE_ERROR_RAD_S = math.radians(60.0)
"""The yaw error at which :data:`YAW_RESERVE` is kept in full."""

COLLECTIVE_MARGIN_M = 1.0
"""Height above the ground at which the collective oracle aims to have stopped sinking (m)."""

COLLECTIVE_BRAKE_FRACTION = 0.5
"""Share of the upright thrust margin ``T_max / m - g`` its braking distance assumes."""


def collective_command(
    pilot: float,
    *,
    altitude_m: float,
    climb_rate_m_s: float,
    cos_tilt: float,
    brake_m_s2: float,
    idle: float,
) -> float:
    """The collective oracle's collective (normalised, in ``[idle, 1]``).

    ``idle`` when the thrust points down (``cos_tilt <= 0``: any thrust pushes the
    vehicle towards the ground); full when it points up and the vehicle, sinking
    at ``v``, is within ``COLLECTIVE_MARGIN_M + v^2 / (2 brake_m_s2)`` of the
    ground; the pilot's otherwise (at least ``idle``).
    """
    if cos_tilt <= 0.0:
        return idle
    sink = -climb_rate_m_s
    if sink > 0.0 and altitude_m < COLLECTIVE_MARGIN_M + sink * sink / (2.0 * brake_m_s2):
        return 1.0
    return min(max(pilot, idle), 1.0)


class OracleController:
    """The oracle law (see the module docstring), behind the shipped laws' interface.

    Parameters
    ----------
    plant
        The vehicle really flown (its physics, damage included).
    period_s
        The interval the command is held (the IMU period), s.
    collective
        Also set the collective (:func:`collective_command`).
    """

    def __init__(
        self,
        plant: VehicleProfile,
        *,
        period_s: float,
        collective: bool = False,
        kappa: float = KAPPA,
        yaw_reserve: float = YAW_RESERVE,
    ) -> None:
        from sitl.envelope import angular_accel_limits_rad_s2

        if not period_s > 0.0:
            raise ValueError(f"period_s: expected > 0, got {period_s!r}")
        self.mixer = build_mixer(plant)
        self.yaw_share = YawShare(0.0)
        """Never offered: the oracle allocates yaw itself (``yaw_reserve``)."""
        self.on_ground = False
        self.nonfinite_events = 0
        self.dt_clamped_events = 0
        self.collective = bool(collective)
        self.h_s = float(period_s)
        self.kappa = float(kappa)
        self.yaw_reserve = float(yaw_reserve)
        P = VehicleParams.from_profile(plant)
        self.params = P
        n = P.n_motors
        self._Jt = P.inertia_kg_m2
        self._Jinv_t = P.inertia_inv
        self._jr = P.rotor_inertia_kg_m2
        self._sigma_t = P.spin_sign
        self._imb = np.array(P.imbalance_coeff)
        self._has_imb = bool(np.any(self._imb > 0.0))
        # Per motor, torque per unit w^2 about (roll, pitch, yaw): the rotor
        # thrust's moment about the CG and the drag torque.
        self._tq_w2_t = tuple(
            (-a[1] * kt, a[0] * kt, sg * kq)
            for a, kt, kq, sg in zip(P.arm_frd_m, P.thrust_coeff, P.torque_coeff, P.spin_sign)
        )
        rf, pf, yf = self.mixer.factors()
        # d command_i / d (roll, pitch, yaw) request, unsaturated.
        self._mix_lin_t = tuple((0.5 * r, 0.5 * p, 0.5 * y) for r, p, y in zip(rf, pf, yf))
        self._span = P.w_max_rad_s - P.w_idle_rad_s
        self._tau_rp = 0.5 * (P.tau_up_s + P.tau_down_s)
        self._dec_up = math.exp(-self.h_s / P.tau_up_s)
        self._dec_down = math.exp(-self.h_s / P.tau_down_s)
        limits = angular_accel_limits_rad_s2(plant)
        self._limits = ((-limits[0][1], limits[0][0]), (-limits[1][1], limits[1][0]))
        self._u: tuple[float, float, float] = _ZERO3
        self._cut = _NO_CUT
        self._scale = [1.0] * n
        self._fail_done = [t is None for t in P.fail_at_s]
        thrust_max = sum(P.thrust_coeff) * P.w_max_rad_s**2
        margin = thrust_max / P.mass_kg - GRAVITY_M_S2
        self._brake_m_s2 = max(COLLECTIVE_BRAKE_FRACTION * margin, 0.1)
        self._quad: Any = None

    # --------------------------------------------------------------- interface
    def see_plant(self, quad: Any) -> None:
        """Called by the simulation loop before each :meth:`update` (reads only)."""
        self._quad = quad

    def reset(self) -> None:
        self._u = _ZERO3

    @property
    def reference_rate_dot(self) -> tuple[float, float, float]:
        return _ZERO3

    def learn(self) -> None:
        """Nothing to learn: the oracle knows the plant."""

    def identified(
        self,
    ) -> tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]:
        """No model identified: it reads the plant (NaN, as the PID's)."""
        nan3 = (math.nan, math.nan, math.nan)
        return (nan3, nan3, nan3)

    @property
    def held_on_ground(self) -> bool:
        """:attr:`on_ground` (the rate-controller interface; as the PID's)."""
        return self.on_ground

    def teach_applied(self, torque: tuple[float, float, float]) -> None:
        """Nothing to teach: it knows the plant (the rate-controller interface)."""

    def update(
        self,
        dt_s: float,
        gyro: tuple[float, float, float],
        ref: tuple[float, float, float],
        thrust: float,
    ) -> ControlOutput:
        """One IMU sample: the gyro is ignored, the true state read from the plant."""
        if self._quad is None:
            raise RuntimeError("the oracle flies only with the plant in view (see_plant)")
        if not (all(math.isfinite(v) for v in ref) and math.isfinite(thrust)):
            # The sticks always map to finite numbers; a NaN is no request.
            self.nonfinite_events += 1
            ref = (
                ref[0] if math.isfinite(ref[0]) else 0.0,
                ref[1] if math.isfinite(ref[1]) else 0.0,
                ref[2] if math.isfinite(ref[2]) else 0.0,
            )
            thrust = thrust if math.isfinite(thrust) else 0.0
        quad = self._quad
        st = quad.state
        w0 = st.motor_w_rad_s
        t_cmd = thrust
        if self.collective:
            _, qx, qy, _ = st.q_wxyz
            t_cmd = collective_command(
                thrust,
                altitude_m=-st.pos_ned_m[2],
                climb_rate_m_s=-st.vel_ned_m_s[2],
                cos_tilt=1.0 - 2.0 * (qx * qx + qy * qy),
                brake_m_s2=self._brake_m_s2,
                idle=self.mixer.idle,
            )
        self._update_failures(st.t_s)
        omega = st.rate_frd_rad_s
        if self._has_imb:
            osc = self._imbalance_rate(w0, quad.rotor_phase_rad)
            omega = (omega[0] - osc[0], omega[1] - osc[1], omega[2] - osc[2])
        if st.landed:
            # On the ground the body cannot turn: no torque to ask for (the model of
            # a free body would chase rates the ground holds at zero).
            u = self._u = _ZERO3
            self._cut = _NO_CUT
        else:
            u = self._solve(omega, w0, ref, t_cmd)
        mix = self.mixer.mix(t_cmd, u[0], u[1], u[2])
        sat, cut = mix.saturated_axes, self._cut
        return ControlOutput(
            mix.achieved,
            mix.thrust,
            mix.motors,
            (sat[0] or cut[0], sat[1] or cut[1], sat[2] or cut[2]),
            mix.saturated_motors,
            u,
            _ZERO3,
            (omega[0] - ref[0], omega[1] - ref[1], omega[2] - ref[2]),
            False,
        )

    # ------------------------------------------------------------------ model
    def yaw_reaction_ratio(self) -> float:
        """``T / tau``: ``T = J_r / (dQ/ds)`` at hover over the slower motor time constant.

        Above 1, the yaw rate can be held once reached (the dead-beat yaw law is
        time-optimal); below, it would need braking like roll and pitch."""
        P = self.params
        w_h = math.sqrt(P.mass_kg * GRAVITY_M_S2 / sum(P.thrust_coeff))
        dq_ds = 2.0 * sum(P.torque_coeff) / P.n_motors * w_h
        return P.rotor_inertia_kg_m2 / dq_ds / max(P.tau_up_s, P.tau_down_s)

    def _update_failures(self, t_s: float) -> None:
        P = self.params
        for i, t_fail in enumerate(P.fail_at_s):
            if not self._fail_done[i] and t_fail is not None and t_s >= t_fail - 1e-9:
                self._fail_done[i] = True
                self._scale[i] = P.speed_scale_after_fail[i]

    def _imbalance_rate(
        self, w: tuple[float, ...], phase: tuple[float, ...]
    ) -> tuple[float, float, float]:
        """The body rate the rotating imbalance forces add, oscillating at the rotor speed."""
        ph = np.array(phase)
        c, s = np.cos(ph), np.sin(ph)
        amp = np.array(self._sigma_t) * self._imb * np.array(w)
        arm = np.array(self.params.arm_frd_m)
        x, y, z = arm[:, 0], arm[:, 1], arm[:, 2]
        H = (
            float(np.sum(-amp * z * c)),
            float(np.sum(-amp * z * s)),
            float(np.sum(amp * (x * c + y * s))),
        )
        return _mat_vec(self._Jinv_t, H)

    def _solve(
        self,
        omega: tuple[float, float, float],
        w0: tuple[float, ...],
        ref: tuple[float, float, float],
        t_cmd: float,
    ) -> tuple[float, float, float]:
        """Normalised roll, pitch, yaw torque requests (see the module docstring).

        Block Newton steps in the mixer's own order: roll and pitch together,
        then yaw with what they leave, each evaluated on the motor commands the
        mixer really makes (so a request is never judged by a command the
        mixer would not send) and clipped to the request range. Plain floats:
        this runs at every IMU sample."""
        J, Jinv, D = self._Jt, self._Jinv_t, self.params.drag_angular
        p, q, r = omega
        Lx = J[0][0] * p + J[0][1] * q + J[0][2] * r
        Ly = J[1][0] * p + J[1][1] * q + J[1][2] * r
        Lz = (
            J[2][0] * p
            + J[2][1] * q
            + J[2][2] * r
            - self._jr * sum(sg * w for sg, w in zip(self._sigma_t, w0))
        )
        L = (Lx, Ly, Lz)
        # Gyroscopic and drag moments, and the acceleration they take away.
        ext = (q * Lz - r * Ly + D[0] * p, r * Lx - p * Lz + D[1] * q, p * Ly - q * Lx + D[2] * r)
        b = _mat_vec(Jinv, ext)
        # Braking authority of roll and pitch, net of those moments: the
        # acceleration the opposite full command gives (kept > 0 so the law
        # stays defined when gyroscopic moments exceed the authority).
        # Yaw's share of the motors' range, kept from roll and pitch while its
        # error is large (see YAW_RESERVE); their braking counts on the rest.
        reserve = self.yaw_reserve * min(1.0, abs(ref[2] - r) / YAW_RESERVE_ERROR_RAD_S)
        keep = 1.0 - reserve
        brake = tuple(
            (max(keep * hi - b[ax], 1e-3), max(b[ax] - keep * lo, 1e-3))
            for ax, (lo, hi) in enumerate(self._limits)
        )
        room = keep * (1.0 - self.mixer.idle)
        u0, u1, u2 = self._u
        cut = [False, False, False]
        for _ in range(_NEWTON_STEPS):
            res, jac = self._residual((u0, u1, u2), t_cmd, w0, L, ext, b, brake, ref)
            a11, a12, a21, a22 = jac[0][0], jac[0][1], jac[1][0], jac[1][1]
            det = a11 * a22 - a12 * a21
            if det != 0.0:
                want0 = u0 - (a22 * res[0] - a12 * res[1]) / det
                want1 = u1 - (a11 * res[1] - a21 * res[0]) / det
                u0, u1 = min(max(want0, -1.0), 1.0), min(max(want1, -1.0), 1.0)
                if self._spread(u0, u1) > room:
                    u0, u1 = self._share(u0, u1, abs(res[0]) >= abs(res[1]), room)
                cut[0], cut[1] = abs(u0 - want0) > 1e-9, abs(u1 - want1) > 1e-9
            res, jac = self._residual((u0, u1, u2), t_cmd, w0, L, ext, b, brake, ref)
            if jac[2][2] > 0.0:
                want2 = u2 - res[2] / jac[2][2]
                u2 = min(max(want2, -1.0), 1.0)
                cut[2] = u2 != want2
        self._u = (u0, u1, u2)
        # Saturated: the law wanted more than it sent (the mixer flags only what it
        # had to cut itself, and the requests above are already cut to fit).
        self._cut = (cut[0], cut[1], cut[2])
        return self._u

    def _spread(self, roll: float, pitch: float) -> float:
        """Range of the motor commands a roll and pitch request spans (the mixer's)."""
        d = [mr * roll + mp * pitch for mr, mp, _ in self._mix_lin_t]
        return max(d) - min(d)

    def _share(self, u0: float, u1: float, roll_first: bool, room: float) -> tuple[float, float]:
        """Roll and pitch requests that fit ``room``: the axis further from its
        reference first, the other with what is left (the mixer would scale both
        down together, and a small correction on one axis would then cost the
        other's flip half its authority)."""
        first, second = (u0, u1) if roll_first else (u1, u0)

        def spread(a: float, b: float) -> float:
            return self._spread(a, b) if roll_first else self._spread(b, a)

        full = spread(first, 0.0)
        if full > room:
            first *= room / full
        lo, hi = 0.0, 1.0
        if spread(first, second) > room:
            for _ in range(20):  # the spread is convex in the second's share
                mid = 0.5 * (lo + hi)
                if spread(first, mid * second) > room:
                    hi = mid
                else:
                    lo = mid
            second *= lo
        return (first, second) if roll_first else (second, first)

    def _stop_term(self, a: float, brake: tuple[float, float]) -> tuple[float, float]:
        """How far the rate still goes when braking from acceleration ``a``, and its slope.

        ``tau (a - A ln(1 + a / A))`` under full opposite command (``A`` its
        authority) through the lag ``tau``; at least ``kappa tau a``."""
        tau_b, kappa = self._tau_rp, self.kappa
        A = brake[1] if a > 0.0 else brake[0]
        x = abs(a) / A
        g = abs(a) - A * math.log1p(x)
        if g >= kappa * abs(a):
            return tau_b * math.copysign(g, a), tau_b * x / (1.0 + x)
        return tau_b * kappa * a, tau_b * kappa

    def _residual(
        self,
        u: tuple[float, float, float],
        t_cmd: float,
        w0: tuple[float, ...],
        L: tuple[float, float, float],
        ext: tuple[float, float, float],
        b: tuple[float, float, float],
        brake: tuple[tuple[float, float], ...],
        ref: tuple[float, float, float],
    ) -> tuple[tuple[float, float, float], list[list[float]]]:
        """What the request ``u`` misses by, and its slope in ``u`` (3 x 3).

        Roll and pitch: where the rate would stop, braking at full opposite
        command from the end of the interval; yaw: the rate at the end of the
        interval; each minus the reference. Slopes through the unsaturated mixer."""
        P = self.params
        Jinv, h, jr = self._Jinv_t, self.h_s, self._jr
        w_idle, span = P.w_idle_rad_s, self._span
        motors = self.mixer.mix(t_cmd, u[0], u[1], u[2]).motors
        imp = [0.0, 0.0, 0.0]  # mean rotor torque over the interval
        end = [0.0, 0.0, 0.0]  # rotor torque at its end
        s_end = 0.0
        d_imp: list[tuple[float, float, float]] = []  # d (h imp + J_r s e_z) / d wc_i
        d_end: list[tuple[float, float, float]] = []  # d end / d wc_i
        for i, (c, wi) in enumerate(zip(motors, w0)):
            wc = self._scale[i] * (w_idle + c * span)
            if wc >= wi:
                dec, tau = self._dec_up, P.tau_up_s
            else:
                dec, tau = self._dec_down, P.tau_down_s
            dw = wi - wc
            w_end = wc + dw * dec
            one = 1.0 - dec
            # Mean w^2 over the interval under the exact first-order lag, and its
            # slope in wc: the rotor torques' impulse over the interval.
            m = wc * wc + (2.0 * wc * dw * tau * one + dw * dw * 0.5 * tau * (1.0 - dec * dec)) / h
            dm = 2.0 * wc + (2.0 * tau * one * (dw - wc) - dw * tau * (1.0 - dec * dec)) / h
            cx, cy, cz = self._tq_w2_t[i]
            e2 = w_end * w_end
            imp[0] += cx * m
            imp[1] += cy * m
            imp[2] += cz * m
            end[0] += cx * e2
            end[1] += cy * e2
            end[2] += cz * e2
            sg = self._sigma_t[i]
            s_end += sg * w_end
            hd = h * dm
            d_imp.append((hd * cx, hd * cy, hd * cz + jr * sg * one))
            de = 2.0 * w_end * one
            d_end.append((de * cx, de * cy, de * cz))
        # The rates at the end of the interval, L' = tau - omega x L - D omega and
        # omega = J^-1 (L - h_r) with h_r = -J_r s e_z; the acceleration there.
        rate_end = _mat_vec(
            Jinv,
            (
                L[0] + h * (imp[0] - ext[0]),
                L[1] + h * (imp[1] - ext[1]),
                L[2] + h * (imp[2] - ext[2]) + jr * s_end,
            ),
        )
        acc = _mat_vec(Jinv, (end[0], end[1], end[2]))
        t0, k0 = self._stop_term(acc[0] - b[0], brake[0])
        t1, k1 = self._stop_term(acc[1] - b[1], brake[1])
        res = (rate_end[0] + t0 - ref[0], rate_end[1] + t1 - ref[1], rate_end[2] - ref[2])
        jac = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
        for i in range(len(motors)):
            dr = _mat_vec(Jinv, d_imp[i])
            da = _mat_vec(Jinv, d_end[i])
            g = self._scale[i] * span
            col = (g * (dr[0] + k0 * da[0]), g * (dr[1] + k1 * da[1]), g * dr[2])
            mr, mp, my = self._mix_lin_t[i]
            for row in range(3):
                jac[row][0] += col[row] * mr
                jac[row][1] += col[row] * mp
                jac[row][2] += col[row] * my
        return res, jac


def _mat_vec(
    m: tuple[tuple[float, float, float], ...], v: tuple[float, float, float]
) -> tuple[float, float, float]:
    return (
        m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
        m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
        m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
    )


def fly_oracle(
    plant: VehicleProfile,
    scenario: Scenario,
    *,
    seed: int | None = None,
    collective: bool = False,
    link: LinkSpec | None = None,
    sticks: MfcConfig | PidConfig | None = None,
    progress: Callable[[float], None] | None = None,
) -> FlightRecord:
    """Fly the oracle on ``scenario``; the :class:`~sitl.lab.simulate.FlightRecord`.

    Parameters
    ----------
    plant
        The vehicle flown; the oracle is given its physics.
    scenario
        Pilot, duration, wind, IMU, link and seed, as for any flight.
    seed
        Overrides ``scenario.seed``.
    collective
        The feasibility judge: the oracle also sets the collective.
    link
        The companion link; default the scenario's.
    sticks
        The controller file whose stick map turns the pilot's sticks into the
        reference (default: the shipped MFC file, as the paper flights).
    """
    from companion.config import load_controller
    from sitl.lab.simulate import simulate_flight

    sc = scenario if link is None else scenario.model_copy(update={"link": link})
    cfg = sticks if sticks is not None else load_controller()
    law = OracleController(plant, period_s=1.0 / sc.imu_model(plant).rate_hz, collective=collective)
    record = simulate_flight(plant, cfg, sc, seed=seed, progress=progress, law=law)
    record.meta["controller"] = "oracle+collective" if collective else "oracle"
    return record


def oracle_flight(
    plant: VehicleProfile,
    scenario: Scenario,
    *,
    seed: int | None = None,
    collective: bool = False,
    link: LinkSpec | None = None,
    sticks: MfcConfig | PidConfig | None = None,
) -> dict[str, Any]:
    """The oracle's flight metrics (:func:`sitl.lab.report.compute_metrics`'s keys).

    ``metrics["crashed"]`` with ``collective=True`` is the feasibility verdict:
    a case where the collective oracle crashes is infeasible.
    """
    from sitl.lab.report import compute_metrics

    return compute_metrics(
        fly_oracle(plant, scenario, seed=seed, collective=collective, link=link, sticks=sticks)
    )
