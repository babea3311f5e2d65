"""Flight modes on the sample path: what the sticks ask, and the estimates it takes.

A part of :class:`companion.app.Companion` (mixed in, below the sample path).
``--mode rates`` (the default) needs nothing here: the sticks are the rate
loop's reference. The other modes put the outer loops between the sticks and
the rate loop, and fly on the autopilot's estimates:

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
stack is known, from its parameters (:meth:`ModePath._build_mode_laws`,
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
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

from companion.control.angle_mode import AngleMode
from companion.control.hold_modes import HoldMode
from companion.control.stick_limits import StickLimits
from companion.engagement import Engagement
from companion.mission import MissionPath

if TYPE_CHECKING:
    from companion.app import RunOptions
    from companion.step import SampleStep

__all__ = ["ModePath"]

Vec3 = tuple[float, float, float]

_ZERO3: Vec3 = (0.0, 0.0, 0.0)
_NAN = math.nan
NO_OUTER_LOG: tuple[float, ...] = (_NAN,) * 13
"""The control log's outer-loop columns when nothing is known (``--mode rates``)."""
_AUTOPILOT_THRUST_FRESH_S = 0.5
"""The autopilot's own collective (ATTITUDE_TARGET) is taken over only this fresh."""
_AUTOPILOT_THRUST_TAU_S = 0.3
"""... and averaged over this (its collective, streamed at 20 Hz, moves each message)."""


class ModePath(Engagement):
    """The flight mode's law and the estimates it flies on (mixed into the app)."""

    imu_rate_hz: float | None
    n_estimate_invalid: int
    _restart_dt: bool
    _rc_needed: bool
    step: SampleStep
    _deflection: tuple[float, float, float]
    _thrust: float

    def _init_modes(self, opts: RunOptions) -> None:
        self.flight_mode = opts.mode
        self.angle: AngleMode | None = None
        self.hold: HoldMode | None = None
        """The flight mode's law, built once the stack's stick limits are known."""
        self.stick_limits: StickLimits | None = None
        self.hover_thrust_prior: float | None = None
        """The autopilot's hover thrust (its parameter), the vertical loop's prior."""
        self.needs_attitude = opts.mode != "rates"
        self.needs_position = opts.mode in ("altitude", "position")
        self.setpoints_flown = False
        """The autopilot flies our setpoints (it accepted the engage mode, and the
        arming if asked); until then, commanding, the laws track the vehicle."""
        self._autopilot_thrust: tuple[float, float] | None = None
        """(wall time, collective) of the autopilot's last ATTITUDE_TARGET."""
        self._stale_estimate_s = opts.failsafe.stale_estimate_s
        self._stale_position_s = opts.failsafe.stale_position_s
        self.n_position_invalid = 0
        self.mode_before_engaging: int | None = None
        """The autopilot's ``custom_mode`` as the last engagement began."""
        self.landed_state_seen = False
        """An EXTENDED_SYS_STATE with a landed state came (the modes need it)."""
        self._applied_thrust: float | None = None
        self._rate_saturated: tuple[bool, bool, bool] | None = None
        """Which axes our rate loop's mixer saturated on the last command sent
        (None: not known: nothing sent, or the autopilot's rate loop flies it)."""
        self.mission = opts.mission
        self.mission_path: MissionPath | None = None
        """The mission as flown from where this engagement started (None before)."""
        self._mission_t = 0.0
        self._mission_reached = 0
        self._mode_events: list[tuple[str, str]] = []
        """Events of this sample, recorded after its command left (_flush_mode_events)."""
        self._dt_typical = 0.0
        """The IMU stream's sample period as it comes (a slow average, gaps bounded)."""
        self._forget_estimates()

    def _build_mode_laws(self, limits: StickLimits, hover_thrust: float | None) -> None:
        """The flight mode's law, with the stack's stick limits and hover thrust."""
        self.stick_limits = limits
        self.hover_thrust_prior = hover_thrust
        if self.flight_mode == "angle":
            self.angle = AngleMode(limits.tilt_max_deg)
        elif self.needs_position:
            self.hold = HoldMode(position=self.flight_mode == "position", limits=limits)
            self.hold.on_ground = bool(self.controller.on_ground)
            self.hold.reset(hover_thrust=hover_thrust)

    def _setpoints_now_flown(self) -> None:
        """The autopilot accepted the engage mode (and the arming, if asked): from
        the next sample it flies our setpoints. The flight modes' laws start here,
        from the vehicle's state (module docstring); rates mode's start at the
        engaged edge."""
        if not self.commanding or self.setpoints_flown:
            return
        if self.needs_attitude:
            self._reset_laws()  # before the flag: the take-over is the autopilot's collective
            self._restart_dt = True
        self.setpoints_flown = True

    @property
    def tracking_the_vehicle(self) -> bool:
        """Commanding, in a flight mode, and the autopilot not flying our setpoints
        yet: the laws start again from the vehicle's state each sample."""
        return self.needs_attitude and self.commanding and not self.setpoints_flown

    def _on_attitude_target(self, msg: Any) -> None:
        """ATTITUDE_TARGET: the collective the autopilot flies (its own, before an
        engagement; ours after), taken over as the hold modes engage: averaged over
        ``_AUTOPILOT_THRUST_TAU_S`` (one message is one instant of a busy loop's
        output)."""
        thrust = float(msg.thrust)
        if not (math.isfinite(thrust) and 0.0 <= thrust <= 1.0):
            return
        now = time.perf_counter()
        got = self._autopilot_thrust
        if got is not None and now - got[0] <= _AUTOPILOT_THRUST_FRESH_S:
            k = min(1.0, (now - got[0]) / _AUTOPILOT_THRUST_TAU_S)
            thrust = got[1] + (thrust - got[1]) * k
        self._autopilot_thrust = (now, thrust)

    def _forget_estimates(self) -> None:
        self._att_q: tuple[float, float, float, float] | None = None
        self._att_age_s = 0.0
        self._pos: tuple[Vec3, Vec3] | None = None
        self._pos_age_s = 0.0

    # ------------------------------------------------------------ the estimates

    def _on_attitude_quaternion(self, v: tuple[Any, ...]) -> None:
        """ATTITUDE_QUATERNION ``(time_boot_ms, q1, q2, q3, q4)`` (a fast handler)."""
        q = (float(v[1]), float(v[2]), float(v[3]), float(v[4]))
        n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
        if not 0.81 <= n2 <= 1.21:  # |q| in [0.9, 1.1]; also False for NaN
            self.n_estimate_invalid += 1
            return
        self._att_q = q
        self._att_age_s = 0.0

    def _on_local_position(self, msg: Any) -> bool:
        """LOCAL_POSITION_NED: position and velocity, NED; returns whether it was
        finite (a position at all)."""
        p = (float(msg.x), float(msg.y), float(msg.z))
        v = (float(msg.vx), float(msg.vy), float(msg.vz))
        if not math.isfinite(p[0] + p[1] + p[2] + v[0] + v[1] + v[2]):
            self.n_position_invalid += 1
            return False
        if self.needs_position:
            self._pos = (p, v)
            self._pos_age_s = 0.0
        return True

    def estimate_fresh(self) -> bool:
        """Whether there is an attitude estimate that came within ``stale_estimate_s``."""
        return self._att_q is not None and self._att_age_s <= self._stale_estimate_s

    def position_fresh(self) -> bool:
        """Whether there is a position estimate that came within ``stale_position_s``."""
        return self._pos is not None and self._pos_age_s <= self._stale_position_s

    def _age_estimates(self, dt: float) -> None:
        """Each sample ages the estimates by its dt, at most two typical periods of
        the IMU stream as it really comes (module docstring). The typical period
        follows the stream slowly (2 % a sample) and a gap moves it at most by
        its own 4 periods' worth: an autopilot that sends 50 Hz when asked 400 Hz
        is learnt within a second or two, one gap of a second is not."""
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

    # ------------------------------------------------------------------ the laws

    def _mode_reference(
        self, dt: float, gyro: Vec3, ref: Vec3, thrust: float
    ) -> tuple[Vec3, float]:
        """This sample's rate reference and collective in the flight mode (``ref`` and
        ``thrust``: the pilot's). Without fresh estimates: no rates and the pilot's
        collective (the rate loop holds the attitude it has), and, engaged, a
        failsafe."""
        self._age_estimates(dt)
        # The loops learn from the gyro as the rate law does: not beyond its range.
        lim = self.step.gyro_limit_rad_s
        g0, g1, g2 = gyro
        if not (-lim <= g0 <= lim and -lim <= g1 <= lim and -lim <= g2 <= lim):
            gyro = (math.nan, math.nan, math.nan)
        stale = self._stale_estimates()
        if stale is not None:
            if self.engaged or self.commanding:
                self._failsafe(*stale)
            self._reset_modes(thrust)
            return _ZERO3, thrust
        q = self._att_q
        assert q is not None
        if self.angle is None and self.hold is None:
            return _ZERO3, thrust  # the stack's limits not read yet: nothing engages
        on_ground = bool(self.controller.on_ground)
        if self.controller.held_on_ground:
            # On its legs the rate law starts afresh (MfcController.on_ground: the MFC
            # law does it itself; a PID restarts here): its F from the air (a damaged
            # motor's torque) would hold that torque on the ground, saturate the
            # mixer and cut the collective, and a vehicle that touched down after a
            # hop never lifted off. Only while the legs visibly hold it
            # (MfcController.held_on_ground): the landed state comes late.
            self.controller.reset()
        if self.angle is not None:
            return self.angle.reference(
                dt, q, gyro, self._deflection, ref[2], on_ground=on_ground,
                rate_saturated=self._rate_saturated,
            ), thrust  # fmt: skip
        hold = self.hold
        assert hold is not None and self._pos is not None
        pos, vel = self._pos
        if self.mission is not None and self.engaged:
            cmd = self._fly_mission(dt, q, gyro, pos, vel)
            return cmd.rate_ref_frd_rad_s, cmd.thrust
        cmd = hold.update(
            dt, q, gyro, pos, vel, self._deflection, thrust, ref[2],
            applied_thrust=self._applied_thrust, rate_saturated=self._rate_saturated,
        )  # fmt: skip
        return cmd.rate_ref_frd_rad_s, cmd.thrust

    def _fly_mission(self, dt: float, q: Any, gyro: Vec3, pos: Vec3, vel: Vec3) -> Any:
        """The mission's setpoint, from where this engagement started; its clock
        runs while the vehicle is in the air."""
        hold, mission = self.hold, self.mission
        assert hold is not None and mission is not None
        path = self.mission_path
        if path is None:
            path = self.mission_path = MissionPath(mission, pos, hold.limits.climb)
            self._mission_t = 0.0
            self._mission_reached = 0
            self._mode_events.append((
                "mission_started",
                # The lab reads the start back from this text (sitl/lab/outer_report.py).
                f"{len(mission.waypoints)} waypoints from N {pos[0]:.2f} E {pos[1]:.2f} "
                f"D {pos[2]:.2f} m, {path.duration_s:.1f} s",
            ))  # fmt: skip
        if not self.controller.on_ground:
            self._mission_t += dt
        t = self._mission_t
        reached = path.waypoints_reached(t)
        if reached > self._mission_reached:
            self._mission_reached = reached
            done = reached == len(mission.waypoints)
            self._mode_events.append((
                "mission_waypoint",
                f"{reached} of {len(mission.waypoints)}" + (": holding there" if done else ""),
            ))  # fmt: skip
        take_off = path.target_at(t)[2] < pos[2] - 0.3  # the waypoint flown to is above
        return hold.fly(
            dt, q, gyro, pos, vel, path.at(t), take_off=take_off,
            applied_thrust=self._applied_thrust, rate_saturated=self._rate_saturated,
        )  # fmt: skip

    def _stale_estimates(self) -> tuple[str, str] | None:
        """The failsafe an estimate's age calls for, or None."""
        if self._att_q is None or self._att_age_s > self._stale_estimate_s:
            age = "none yet" if self._att_q is None else f"the last {self._att_age_s:.3f} s ago"
            return (
                "failsafe_stale_estimate",
                f"no valid attitude estimate (ATTITUDE_QUATERNION) for "
                f"{self._stale_estimate_s} s of IMU time ({age})",
            )
        if self.needs_position and (self._pos is None or self._pos_age_s > self._stale_position_s):
            age = "none yet" if self._pos is None else f"the last {self._pos_age_s:.3f} s ago"
            return (
                "failsafe_stale_position",
                f"no valid position estimate (LOCAL_POSITION_NED) for "
                f"{self._stale_position_s} s of IMU time ({age})",
            )
        return None

    def _pilot_fresh(self) -> bool:
        """A valid frame of the pilot's input came within the RC timeout."""
        rc = self._rc_wall
        return rc is not None and time.perf_counter() - rc <= self.opts.failsafe.rc_timeout_s

    def _not_ready_to_engage(self) -> str | None:
        """Why the vehicle must not be engaged now, or None."""
        if self.needs_attitude and self.angle is None and self.hold is None:
            return f"--mode {self.flight_mode}: the autopilot's stick limits not read yet"
        if self.opts.engage == "auto" and self._rc_needed and not self._pilot_fresh():
            # (With rc-switch the pilot's switch, in their own input, is the engagement.)
            return (
                "no valid pilot input (RC_CHANNELS, or MANUAL_CONTROL from a joystick) "
                "yet: the sticks fly"
            )
        if self.needs_attitude and not self.landed_state_seen:
            return (
                f"no landed state (EXTENDED_SYS_STATE) yet: --mode {self.flight_mode} holds "
                "its loops on the ground by it"
            )
        if self.needs_attitude and not self.estimate_fresh():
            return (
                f"no fresh attitude estimate (ATTITUDE_QUATERNION): --mode {self.flight_mode} "
                "flies on it; is the autopilot's estimator running and the stream allowed?"
            )
        if self.needs_position and not self.position_fresh():
            return (
                f"no fresh position estimate (LOCAL_POSITION_NED): --mode {self.flight_mode} "
                "flies on it; has the autopilot a position (GPS, flow) and the stream allowed?"
            )
        return None

    def _reset_modes(self, thrust: float | None = None) -> None:
        """Forget what the outer loops learnt. The hold modes take over at the lowest
        collective on the ground; in the air at :meth:`_take_over_thrust`, with the
        autopilot's hover thrust as the vertical loop's prior."""
        if self.angle is not None:
            self.angle.reset()
        if self.hold is not None:
            on_ground = bool(self.controller.on_ground)
            take_over = 0.0 if on_ground else self._take_over_thrust(thrust)
            q = None if on_ground else self._att_q
            self.hold.reset(thrust=take_over, hover_thrust=self.hover_thrust_prior, q_wxyz=q)
            self._applied_thrust = None
            self._rate_saturated = None
            self.mission_path = None  # an engagement starts the mission from where it is

    def _take_over_thrust(self, pilot_thrust: float | None) -> float | None:
        """The collective the vehicle flies now, for the hold modes to take over at:
        the autopilot's own (ATTITUDE_TARGET, fresh, before it flies ours); else the
        pilot's throttle when the autopilot flew a mode whose throttle is the
        collective; else None (the hover estimate: a mode holding altitude centres
        the throttle stick whatever the vehicle needs)."""
        got = self._autopilot_thrust
        if (
            got is not None
            and not self.setpoints_flown
            and time.perf_counter() - got[0] <= _AUTOPILOT_THRUST_FRESH_S
        ):
            return got[1]
        stack, before = self.stack, self.mode_before_engaging
        manual = stack is not None and before is not None and before in stack.throttle_modes
        return pilot_thrust if manual else None

    def _reset_laws(self) -> None:
        """Forget what the laws learnt: the rate law and the flight mode's loops."""
        self.controller.reset()
        self.step.reset()
        self._reset_modes(self._thrust)

    def _mode_log(self) -> tuple[float, ...]:
        """The control log's outer-loop columns (``companion.records.columns``): the
        attitude setpoint and the attitude estimate (roll, pitch, heading, rad),
        the position setpoint and the position estimate (north, east, up, m), the
        outer gains' scale; NaN for what this mode does not hold or has not got.
        Off the latency path."""
        if self.flight_mode == "rates":
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
        q = self._att_q
        if q is None:
            est_att: tuple[float, float, float] = (_NAN, _NAN, _NAN)
        else:
            w, x, y, z = q
            est_att = (
                math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y)),
                math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x)))),
                math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)),
            )
        est_pos = (_NAN, _NAN, _NAN) if self._pos is None else self._pos[0]
        return (*sp_att, *est_att, *pos_sp, est_pos[0], est_pos[1], -est_pos[2], scale)

    def _flush_mode_events(self) -> None:
        """Record this sample's events (called once its command has left)."""
        for kind, detail in self._mode_events:
            self._event(kind, detail)
        self._mode_events.clear()

    def _mode_on_ground(self, on_ground: bool) -> None:
        """The autopilot's landed state changed."""
        if self.hold is not None:
            self.hold.on_ground = on_ground
