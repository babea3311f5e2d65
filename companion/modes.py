"""Flight modes on the sample path: what the sticks ask, and the estimates it takes.

``--mode rates`` (the default) needs nothing here: the sticks are the rate
loop's reference. The other modes put the outer loops between the sticks and
the rate loop, and fly on the autopilot's estimates; :class:`ModeLaws` holds
them for the flight core (:class:`companion.core.FlightCore`), which owns it:

========== ==================================== =========================================
mode       law (``companion/control``)          estimates
========== ==================================== =========================================
angle      :class:`~.angle_mode.AngleMode`      ``ATTITUDE_QUATERNION``
altitude   :class:`~.hold_modes.HoldMode`       ``ATTITUDE_QUATERNION``, ``LOCAL_POSITION_NED``
position   :class:`~.hold_modes.HoldMode`       ``ATTITUDE_QUATERNION``, ``LOCAL_POSITION_NED``
========== ==================================== =========================================

Each estimate's age is the IMU time flown since a valid one came: each sample
adds its dt, but at most two periods of the IMU stream, so a gap in the whole
stream (datagrams lost, the IMU's as well) is the stale-IMU watchdog's, while
IMU samples that keep coming without an estimate are the estimate's. Beyond
``stale_estimate_s`` (attitude) or ``stale_position_s`` (position), while engaged
or engaging, it is a failsafe (``failsafe_stale_estimate``,
``failsafe_stale_position``); without fresh estimates nothing engages. A
quaternion that is not finite or not near unit norm, or a position or velocity
that is not finite, is not an estimate: counted (``estimate_invalid``,
``position_invalid``), and the last good one ages on.

What the sticks may ask is the autopilot's own: the laws are built once the
stack is known, from its parameters (:meth:`ModeLaws.build`,
:mod:`companion.stacks`).

Taking over without a jolt
--------------------------
The autopilot flies our setpoints only once it has accepted the engage mode
(and, with ``--engage auto``, the arming). Until then the setpoints stream but
are not flown, so nothing the laws would learn from them is true: while
commanding and not yet flown, every sample starts the laws again from the
vehicle's state (the rate law and the outer loops reset; the hold modes take
over at the collective the autopilot flies now, the setpoints at the estimated
velocity, the holds where the vehicle is). The first setpoint the autopilot
flies is that one, and from then on the laws run on: the engaged edge (the
autopilot's heartbeat, up to a second later) does not start them again.

No I/O; the time is the caller's (``now``, the arrival of a message).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from companion.control import RateController
from companion.control.angle_mode import AngleMode
from companion.control.hold_modes import HoldMode
from companion.control.outer import OuterLaw
from companion.control.stick_limits import StickLimits
from companion.failsafe import Verdict
from companion.flight_modes import FlightMode
from companion.mission import FlightPlan, PlannedPath

__all__ = ["NO_OUTER_LOG", "ModeLaws"]

Vec3 = tuple[float, float, float]

_ZERO3: Vec3 = (0.0, 0.0, 0.0)
_NAN = math.nan
NO_OUTER_LOG: tuple[float, ...] = (_NAN,) * 13
"""The control log's outer-loop columns when nothing is known (``--mode rates``)."""
_AUTOPILOT_THRUST_FRESH_S = 0.5
"""The autopilot's own collective (ATTITUDE_TARGET) is taken over only this fresh."""
_AUTOPILOT_THRUST_TAU_S = 0.3
"""... and averaged over this (its collective, streamed at 20 Hz, moves each message)."""


class ModeLaws:
    """The flight mode's law and the estimates it flies on.

    Parameters
    ----------
    mode
        The flight mode (:data:`companion.flight_modes.FLIGHT_MODES`).
    mission
        With ``"position"``: the plan (a mission's waypoints) flown from where an
        engagement starts, instead of the sticks.
    stale_estimate_s, stale_position_s
        How much IMU time an attitude or position estimate may age.
    outer_law
        Makes the outer loops the altitude and position modes fly instead of
        their own (the lab's baseline, PX4's default cascade).
    """

    def __init__(
        self,
        mode: FlightMode,
        mission: FlightPlan | None,
        *,
        stale_estimate_s: float,
        stale_position_s: float,
        outer_law: Callable[[], OuterLaw] | None = None,
    ) -> None:
        self.mode = mode
        self._outer_law = outer_law
        self.needs_attitude = mode.needs_attitude
        self.needs_position = mode.needs_position
        self.angle: AngleMode | None = None
        self.hold: HoldMode | None = None
        """The flight mode's law, built once the stack's stick limits are known."""
        self.stick_limits: StickLimits | None = None
        self.hover_thrust_prior: float | None = None
        """The autopilot's hover thrust (its parameter), the vertical loop's prior."""
        self.autopilot_thrust: tuple[float, float] | None = None
        """(arrival time, collective) of the autopilot's last ATTITUDE_TARGET."""
        self._stale_estimate_s = stale_estimate_s
        self._stale_position_s = stale_position_s
        self.n_estimate_invalid = 0
        self.n_position_invalid = 0
        self.landed_state_seen = False
        """An EXTENDED_SYS_STATE with a landed state came (the modes need it)."""
        self.applied_thrust: float | None = None
        self.rate_saturated: tuple[bool, bool, bool] | None = None
        """Which axes our rate loop's mixer saturated on the last command sent
        (None: not known: nothing sent, or the autopilot's rate loop flies it)."""
        self.mission = mission
        self.mission_path: PlannedPath | None = None
        """The mission as flown from where this engagement started (None before)."""
        self.mission_t = 0.0
        self._mission_reached = 0
        self.events: list[tuple[str, str]] = []
        """Events of this sample, for the caller to record once its command has left."""
        self.imu_rate_hz: float | None = None
        """The IMU stream's rate as asked (the first guess of its period)."""
        self._dt_typical = 0.0
        """The IMU stream's sample period as it comes (a slow average, gaps bounded)."""
        self.forget_estimates()

    def build(self, limits: StickLimits, hover_thrust: float | None, *, on_ground: bool) -> None:
        """The flight mode's law, with the stack's stick limits and hover thrust."""
        self.stick_limits = limits
        self.hover_thrust_prior = hover_thrust
        outer = None if self._outer_law is None else self._outer_law()
        law = None if self.mode.law is None else self.mode.law(limits, outer)
        if isinstance(law, AngleMode):
            self.angle = law
        elif law is not None:
            self.hold = law
            law.on_ground = on_ground
            law.reset(hover_thrust=hover_thrust)

    @property
    def built(self) -> bool:
        """The law exists (the stack's limits were read)."""
        return self.angle is not None or self.hold is not None

    # ------------------------------------------------------------ the estimates

    def on_attitude_target(self, thrust: float, now: float) -> None:
        """ATTITUDE_TARGET's collective: what the autopilot flies (its own, before an
        engagement; ours after), taken over as the hold modes engage: averaged over
        ``_AUTOPILOT_THRUST_TAU_S`` (one message is one instant of a busy loop's
        output)."""
        if not (math.isfinite(thrust) and 0.0 <= thrust <= 1.0):
            return
        got = self.autopilot_thrust
        if got is not None and now - got[0] <= _AUTOPILOT_THRUST_FRESH_S:
            k = min(1.0, (now - got[0]) / _AUTOPILOT_THRUST_TAU_S)
            thrust = got[1] + (thrust - got[1]) * k
        self.autopilot_thrust = (now, thrust)

    def forget_estimates(self) -> None:
        self.att_q: tuple[float, float, float, float] | None = None
        self._att_age_s = 0.0
        self.pos: tuple[Vec3, Vec3] | None = None
        self._pos_age_s = 0.0

    def on_attitude_quaternion(self, v: tuple[Any, ...]) -> None:
        """ATTITUDE_QUATERNION ``(time_boot_ms, q1, q2, q3, q4)``."""
        q = (float(v[1]), float(v[2]), float(v[3]), float(v[4]))
        n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
        if not 0.81 <= n2 <= 1.21:  # |q| in [0.9, 1.1]; also False for NaN
            self.n_estimate_invalid += 1
            return
        self.att_q = q
        self._att_age_s = 0.0

    def on_local_position(self, msg: Any) -> bool:
        """LOCAL_POSITION_NED: position and velocity, NED; returns whether it was
        finite (a position at all)."""
        p = (float(msg.x), float(msg.y), float(msg.z))
        v = (float(msg.vx), float(msg.vy), float(msg.vz))
        if not math.isfinite(p[0] + p[1] + p[2] + v[0] + v[1] + v[2]):
            self.n_position_invalid += 1
            return False
        if self.needs_position:
            self.pos = (p, v)
            self._pos_age_s = 0.0
        return True

    def estimate_fresh(self) -> bool:
        """Whether there is an attitude estimate that came within ``stale_estimate_s``."""
        return self.att_q is not None and self._att_age_s <= self._stale_estimate_s

    def position_fresh(self) -> bool:
        """Whether there is a position estimate that came within ``stale_position_s``."""
        return self.pos is not None and self._pos_age_s <= self._stale_position_s

    def age_estimates(self, dt: float) -> Verdict | None:
        """Each sample ages the estimates by its dt, at most two typical periods of
        the IMU stream as it really comes (module docstring). The typical period
        follows the stream slowly (2 % a sample) and a gap moves it at most by
        its own 4 periods' worth: an autopilot that sends 50 Hz when asked 400 Hz
        is learnt within a second or two, one gap of a second is not. Returns the
        failsafe their ages call for (:meth:`stale`), or None."""
        typ = self._dt_typical
        if typ <= 0.0:
            hz = self.imu_rate_hz
            typ = 1.0 / hz if hz else dt
        if dt > 0.0:
            typ += 0.02 * (min(dt, 4.0 * typ) - typ)
        self._dt_typical = typ
        step = dt if dt <= 2.0 * typ else 2.0 * typ
        self._att_age_s += step
        self._pos_age_s += step
        return self.stale()

    def stale(self) -> Verdict | None:
        """The failsafe an estimate's age calls for, or None."""
        if self.att_q is None or self._att_age_s > self._stale_estimate_s:
            age = "none yet" if self.att_q is None else f"the last {self._att_age_s:.3f} s ago"
            return (
                "failsafe_stale_estimate",
                f"no valid attitude estimate (ATTITUDE_QUATERNION) for "
                f"{self._stale_estimate_s} s of IMU time ({age})",
            )
        if self.needs_position and (self.pos is None or self._pos_age_s > self._stale_position_s):
            age = "none yet" if self.pos is None else f"the last {self._pos_age_s:.3f} s ago"
            return (
                "failsafe_stale_position",
                f"no valid position estimate (LOCAL_POSITION_NED) for "
                f"{self._stale_position_s} s of IMU time ({age})",
            )
        return None

    def not_ready(self) -> str | None:
        """Why this mode cannot be engaged now (its limits, its estimates), or None."""
        mode = self.mode.name
        if self.needs_attitude and not self.built:
            return f"--mode {mode}: the autopilot's stick limits not read yet"
        return None

    def estimates_missing(self) -> str | None:
        """Which estimate the mode flies on is missing, or None."""
        mode = self.mode.name
        if self.needs_attitude and not self.landed_state_seen:
            return (
                f"no landed state (EXTENDED_SYS_STATE) yet: --mode {mode} holds "
                "its loops on the ground by it"
            )
        if self.needs_attitude and not self.estimate_fresh():
            return (
                f"no fresh attitude estimate (ATTITUDE_QUATERNION): --mode {mode} "
                "flies on it; is the autopilot's estimator running and the stream allowed?"
            )
        if self.needs_position and not self.position_fresh():
            return (
                f"no fresh position estimate (LOCAL_POSITION_NED): --mode {mode} "
                "flies on it; has the autopilot a position (GPS, flow) and the stream allowed?"
            )
        return None

    # ------------------------------------------------------------------ the laws

    def sample_reference(
        self,
        dt: float,
        gyro: Vec3,
        ref: Vec3,
        thrust: float,
        deflection: Vec3,
        controller: RateController,
        *,
        gyro_limit_rad_s: float,
        mission_flown: bool,
    ) -> tuple[Vec3, float]:
        """This sample's rate reference and collective, on fresh estimates: the
        loops learn from the gyro as the rate law does (NaN beyond its range), and
        while the vehicle's legs visibly hold it the rate law starts afresh."""
        q = self.att_q
        assert q is not None
        if not self.built:
            return _ZERO3, thrust  # the stack's limits not read yet: nothing engages
        lim = gyro_limit_rad_s
        g0, g1, g2 = gyro
        if not (-lim <= g0 <= lim and -lim <= g1 <= lim and -lim <= g2 <= lim):
            gyro = (_NAN, _NAN, _NAN)
        on_ground = bool(controller.on_ground)
        if controller.held_on_ground:
            # On its legs the rate law starts afresh (MfcController.on_ground: the MFC
            # law does it itself; a PID restarts here): its F from the air (a damaged
            # motor's torque) would hold that torque on the ground, saturate the
            # mixer and cut the collective, and a vehicle that touched down after a
            # hop never lifted off. Only while the legs visibly hold it
            # (MfcController.held_on_ground): the landed state comes late.
            controller.reset()
        return self.reference(
            dt, q, gyro, ref, thrust, deflection, on_ground=on_ground,
            mission_flown=mission_flown,
        )  # fmt: skip

    def reference(
        self,
        dt: float,
        q: tuple[float, float, float, float],
        gyro: Vec3,
        ref: Vec3,
        thrust: float,
        deflection: Vec3,
        *,
        on_ground: bool,
        mission_flown: bool,
    ) -> tuple[Vec3, float]:
        """This sample's rate reference and collective from the mode's law, on fresh
        estimates (``ref`` and ``thrust``: the pilot's; ``gyro``: NaN where beyond
        the rate law's range). ``mission_flown``: engaged, the mission (if one)
        flies instead of the sticks."""
        if self.angle is not None:
            return self.angle.reference(
                dt, q, gyro, deflection, ref[2], on_ground=on_ground,
                rate_saturated=self.rate_saturated,
            ), thrust  # fmt: skip
        hold = self.hold
        if hold is None:
            return _ZERO3, thrust  # the stack's limits not read yet: nothing engages
        assert self.pos is not None
        pos, vel = self.pos
        if self.mission is not None and mission_flown:
            cmd = self._fly_mission(dt, q, gyro, pos, vel, on_ground=on_ground)
            return cmd.rate_ref_frd_rad_s, cmd.thrust
        cmd = hold.update(
            dt, q, gyro, pos, vel, deflection, thrust, ref[2],
            applied_thrust=self.applied_thrust, rate_saturated=self.rate_saturated,
        )  # fmt: skip
        return cmd.rate_ref_frd_rad_s, cmd.thrust

    def _fly_mission(
        self, dt: float, q: Any, gyro: Vec3, pos: Vec3, vel: Vec3, *, on_ground: bool
    ) -> Any:
        """The mission's setpoint, from where this engagement started; its clock
        runs while the vehicle is in the air."""
        hold, mission = self.hold, self.mission
        assert hold is not None and mission is not None
        path = self.mission_path
        if path is None:
            path = self.mission_path = mission.path(pos, hold.limits)
            self.mission_t = 0.0
            self._mission_reached = 0
            self.events.append((
                "mission_started",
                # The lab reads the start back from this text (sitl/lab/outer_report.py).
                f"{mission.n_waypoints} waypoints from N {pos[0]:.2f} E {pos[1]:.2f} "
                f"D {pos[2]:.2f} m, {path.summary()}",
            ))  # fmt: skip
        if not on_ground:
            self.mission_t += dt
        t = self.mission_t
        reached = path.waypoints_reached(t)
        if reached > self._mission_reached:
            self._mission_reached = reached
            done = reached == mission.n_waypoints
            self.events.append((
                "mission_waypoint",
                f"{reached} of {mission.n_waypoints}" + (": holding there" if done else ""),
            ))  # fmt: skip
        take_off = path.target_at(t)[2] < pos[2] - 0.3  # the waypoint flown to is above
        return hold.fly(
            dt, q, gyro, pos, vel, path.at(t), take_off=take_off,
            applied_thrust=self.applied_thrust, rate_saturated=self.rate_saturated,
        )  # fmt: skip

    def reset(self, take_over_thrust: float | None, *, on_ground: bool) -> None:
        """Forget what the outer loops learnt. The hold modes take over at the lowest
        collective on the ground; in the air at ``take_over_thrust`` (None: the
        hover estimate), with the autopilot's hover thrust as the vertical loop's
        prior."""
        if self.angle is not None:
            self.angle.reset()
        if self.hold is not None:
            take_over = 0.0 if on_ground else take_over_thrust
            q = None if on_ground else self.att_q
            self.hold.reset(thrust=take_over, hover_thrust=self.hover_thrust_prior, q_wxyz=q)
            self.applied_thrust = None
            self.rate_saturated = None
            self.mission_path = None  # an engagement starts the mission from where it is

    def take_over_thrust(
        self, pilot_thrust: float | None, now: float, *, flown: bool, manual_before: bool
    ) -> float | None:
        """The collective the vehicle flies now, for the hold modes to take over at:
        the autopilot's own (ATTITUDE_TARGET, fresh, before it flies ours:
        ``flown`` False); else the pilot's throttle when the autopilot flew a mode
        whose throttle is the collective (``manual_before``); else None (the hover
        estimate: a mode holding altitude centres the throttle stick whatever the
        vehicle needs)."""
        got = self.autopilot_thrust
        if got is not None and not flown and now - got[0] <= _AUTOPILOT_THRUST_FRESH_S:
            return got[1]
        return pilot_thrust if manual_before else None

    def on_ground_changed(self, on_ground: bool) -> None:
        """The autopilot's landed state changed."""
        if self.hold is not None:
            self.hold.on_ground = on_ground

    def log_columns(self) -> tuple[float, ...]:
        """The control log's outer-loop columns (``companion.records.columns``): the
        attitude setpoint and the attitude estimate (roll, pitch, heading, rad),
        the position setpoint and the position estimate (north, east, up, m), the
        outer gains' scale; NaN for what this mode does not hold or has not got.
        Off the latency path."""
        if not self.needs_attitude:
            return NO_OUTER_LOG
        att = None
        pos_sp: tuple[float, float, float] = (_NAN, _NAN, _NAN)
        scale = _NAN
        if self.angle is not None:
            att = self.angle.setpoint
            scale = self.angle.backoff.scale
        elif self.hold is not None:
            att = self.hold.attitude_setpoint
            scale = self.hold.outer.gain_scale
            sp = self.hold.setpoint
            ne = sp.horizontal.position_ne_m
            up = sp.vertical.up_m
            pos_sp = (
                _NAN if ne is None else ne[0],
                _NAN if ne is None else ne[1],
                _NAN if up is None else up,
            )
        if att is None:
            sp_att: tuple[float, float, float] = (_NAN, _NAN, _NAN)
        else:
            yaw = att.yaw_rad
            sp_att = (att.roll_rad, att.pitch_rad, _NAN if yaw is None else yaw)
        q = self.att_q
        if q is None:
            est_att: tuple[float, float, float] = (_NAN, _NAN, _NAN)
        else:
            w, x, y, z = q
            est_att = (
                math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y)),
                math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x)))),
                math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)),
            )
        est_pos = (_NAN, _NAN, _NAN) if self.pos is None else self.pos[0]
        return (*sp_att, *est_att, *pos_sp, est_pos[0], est_pos[1], -est_pos[2], scale)
