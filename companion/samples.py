"""The sample path: each IMU sample, as it arrives, to one command.

A part of :class:`companion.app.Companion` (it is mixed in). Inside the link's
receive callback, with no queue and no task switch: the timestamp checks (late,
duplicate, a gap, a rebooted autopilot's new clock), then the shared step
(:class:`companion.step.SampleStep`: gyro range gate, law, command gate), the
send, and, off the latency path, what the law learns, the failsafes judged per
sample (:class:`companion.failsafe.SampleWatch`) and the record. The pilot's
RC frames and the autopilot's heartbeats arrive here too: the reference, the
engage switch, and whether the vehicle is engaged.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from companion.config import build_stick_map
from companion.control.sticks import joystick_channels
from companion.failsafe import SampleWatch
from companion.link.timesync import LinkClock
from companion.modes import ModePath
from companion.step import NO_RATES, SampleStep, whole_us

if TYPE_CHECKING:
    from companion.app import RunOptions

__all__ = ["SamplePath"]

_log = logging.getLogger("companion.app")

_TIME_JUMP_S = 1.0
"""An IMU time step beyond this, either way, is a discontinuity, not a late
sample or a gap (stale IMU fires after ``stale_imu_s``, far less)."""
_NEW_CLOCK_SAMPLES = 3
"""Samples in a row that must follow on from a jump before it is real (a gap,
or a new clock: an autopilot reboot) rather than one corrupt timestamp: 12 ms
at 250 Hz."""
_STEP_AHEAD_S = 0.02
"""How far one IMU step may run ahead of the wall clock between the two
samples' arrivals and still be flown at once; also the longest step by which
samples follow on from a jump. A longer step is a gap only if the wall clock
took it too, or if the next samples continue from it. 20 ms is five samples at
250 Hz (a few lost in a row pass as they come, even where a lockstep
simulator's clock outruns the wall's), the rate law's own longest time step
(``dt_max_s``), and bounds what one wrong stamp can cost: the genuine samples
it puts behind it are at most this much of the stream."""

# MAVLink numbers used here (common.xml).
_MSG_HEARTBEAT = 0
_MSG_LOCAL_POSITION_NED = 32
_MSG_TIMESYNC = 111
_MSG_EXTENDED_SYS_STATE = 245
_MSG_STATUSTEXT = 253
_MSG_SYS_STATUS = 1
_MSG_ATTITUDE_TARGET = 83
_SENSOR_RC_RECEIVER = 1 << 16  # MAV_SYS_STATUS_SENSOR_RC_RECEIVER
_SENSOR_PREARM_CHECK = 1 << 28  # MAV_SYS_STATUS_PREARM_CHECK
_STATE_NAMES = {5: "CRITICAL", 6: "EMERGENCY"}
_FAILSAFE_STATES = frozenset(_STATE_NAMES)
"""HEARTBEAT ``system_status`` values with which PX4 and ArduPilot say they are
failing safe (MAV_STATE_CRITICAL, MAV_STATE_EMERGENCY), whatever mode they show."""
_BASE_MODE_ARMED = 128
_LANDED_STATE_UNDEFINED = 0  # MAV_LANDED_STATE_UNDEFINED
_LANDED_STATE_ON_GROUND = 1  # MAV_LANDED_STATE_ON_GROUND

AGES_KEPT = 1024
"""The last samples' ages kept for the link's figures (about 1 s at 1 kHz)."""


class SamplePath(ModePath):
    """The per-sample path and its counters (mixed into the app)."""

    # What the app holds and these methods use.
    _log_append: Any
    _telemetry: Any
    imu_rate_hz: float | None

    if TYPE_CHECKING:  # the app's

        async def _rerequest_streams(self, why: str) -> None: ...

    def _init_sample_path(self, opts: RunOptions) -> None:
        self.sticks = build_stick_map(opts.controller)
        # The range gate, the law and the command gate: the lab's flights use the same.
        self.step = SampleStep(
            self.controller,
            opts.profile,
            output=opts.output,
            rates_full_scale_deg_s=opts.rates_full_scale_deg_s,
            rates_lead_s=opts.rates_lead_s,
            rates_passthrough=opts.rates_passthrough,
        )
        self.n_imu = 0
        self.n_imu_duplicate_or_late = 0
        self.n_imu_invalid = 0
        self.n_imu_time_jumps = 0
        self.n_imu_gaps = 0
        self.n_imu_time_outliers = 0
        self.n_imu_clock_resets = 0
        self.n_commands = 0
        self.n_commands_gated = 0
        self.n_sample_errors = 0
        self.n_rc_invalid = 0
        self.n_rc_unhealthy = 0
        self.n_sys_status = 0
        self._joystick_wall: float | None = None
        """When the last MANUAL_CONTROL frame came, valid or not."""
        self._rc_receiver_healthy = True
        self._rc_receiver_seen = False
        self._prearm_ready: bool | None = None
        """The autopilot's pre-arm checks pass, as its SYS_STATUS says; None: it
        says nothing about them (not reported, or no SYS_STATUS yet)."""
        self._ap_status: int | None = None
        """The autopilot's last HEARTBEAT ``system_status`` (MAV_STATE)."""
        """The autopilot's SYS_STATUS says its RC receiver is healthy (or says nothing)."""
        self._rc_radio_wall: float | None = None
        """When the last valid RC_CHANNELS frame came (a radio, not a joystick)."""
        self.n_estimate_invalid = 0
        self._errors_in_row = 0
        self._clock_candidate: tuple[float, int] | None = None
        self._imu_source = opts.imu_source
        self._t_prev: float | None = None
        self._t_engaged: float | None = None
        self._t_first: float | None = None
        self._last_imu_wall: float | None = None
        # The failsafes judged on each sample (in sample time).
        self.watch = SampleWatch(
            opts.failsafe,
            self.step.rate_max_rad_s,
            opts.profile.limits.motor_idle,
            actuator=opts.output == "actuator",
        )
        self._rc: tuple[int, ...] = ()
        self._ref: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._deflection: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._thrust = 0.0
        self._init_modes(opts)
        self._switch_high = False
        self._switch_seen_low = False
        """The engage switch was seen low since start-up: until then, a switch
        that is already high engages nothing (a companion that starts, or
        restarts, in flight with the switch high must not take over at once)."""
        self._switch_said_high = False
        self.started_up = False
        """Start-up is over (the stack recognised, the streams requested): the
        switch is read from then on."""
        self._restart_dt = False
        self._actuator_output = opts.output == "actuator"
        self._script = opts.reference
        self._duration_s = opts.duration_s
        # Counted in the autopilot's whole microseconds: a float difference of two
        # large stamps would end the run one sample early or late by its rounding.
        self._duration_us = None if opts.duration_s is None else round(opts.duration_s * 1e6)
        # The link, measured: TIMESYNC round trips (the app asks), and each
        # sample's age when its command leaves (a ring of the last AGES_KEPT).
        self.link_clock = LinkClock()
        self.sample_ages_s = [float("nan")] * AGES_KEPT
        self._n_ages = 0

    def _on_message(self, msg: Any) -> None:
        # HIGHRES_IMU, ATTITUDE and RC_CHANNELS never come here: run() registers
        # them with the link's fast handlers, which take them on either road.
        mid = msg.get_msgId()
        if mid == _MSG_HEARTBEAT:
            self._on_heartbeat(msg)
        elif mid == _MSG_STATUSTEXT:
            text = msg.text.decode(errors="replace") if isinstance(msg.text, bytes) else msg.text
            self._last_statustext = text.rstrip("\x00")
            self._event("autopilot_says", self._last_statustext)
        elif mid == _MSG_EXTENDED_SYS_STATE:
            self._on_landed_state(int(msg.landed_state))
        elif mid == _MSG_LOCAL_POSITION_NED:
            # A hand-back without RC holds with a valid position: a finite one.
            if self._on_local_position(msg):
                self._pos_wall = time.perf_counter()
        elif mid == _MSG_TIMESYNC and msg.tc1 != 0:
            # An answer to ours (the autopilot's own requests, tc1 = 0, go unanswered).
            self.link_clock.reply(msg.tc1, msg.ts1, self.link.rx_perf_s)
        elif mid == _MSG_SYS_STATUS:
            self._on_sys_status(msg)
        elif mid == _MSG_ATTITUDE_TARGET:
            self._on_attitude_target(msg)

    def _on_sys_status(self, msg: Any) -> None:
        """SYS_STATUS: whether the autopilot's RC receiver is healthy, and whether
        its pre-arm checks pass.

        ArduPilot keeps sending RC_CHANNELS with the last pulses it had after its
        radio is lost; what says it is lost is the RC receiver's health bit
        (cleared when its own radio failsafe triggers). While it is clear, the
        RC_CHANNELS frames are not the pilot's: they do not count as valid RC.

        PX4 and ArduPilot report their pre-arm checks as a sensor
        (MAV_SYS_STATUS_PREARM_CHECK), healthy while they pass: ``--engage
        auto`` waits for it before arming. A stack that does not report it
        (the bit not present) leaves ``_prearm_ready`` None: it is just tried."""
        self.n_sys_status += 1
        present = int(msg.onboard_control_sensors_present)
        if present & _SENSOR_PREARM_CHECK:
            self._prearm_ready = bool(
                int(msg.onboard_control_sensors_health) & _SENSOR_PREARM_CHECK
            ) or not (int(msg.onboard_control_sensors_enabled) & _SENSOR_PREARM_CHECK)
        else:
            self._prearm_ready = None
        bit = _SENSOR_RC_RECEIVER
        if present & bit:
            self._rc_receiver_seen = True
            healthy = bool(int(msg.onboard_control_sensors_health) & bit) or not (
                int(msg.onboard_control_sensors_enabled) & bit
            )
        elif self._rc_receiver_seen:
            healthy = False  # it was there and is gone (PX4 on a radio or joystick loss)
        else:
            return  # no receiver reported at all: nothing to judge by
        if healthy == self._rc_receiver_healthy:
            return
        self._rc_receiver_healthy = healthy
        if healthy:
            self._event("rc_receiver", "the autopilot reports its RC receiver healthy again")
        else:
            self._event(
                "rc_receiver_lost",
                "the autopilot reports its RC receiver unhealthy (SYS_STATUS): its RC_CHANNELS "
                "are the last pulses it had, not the pilot's",
            )

    def _on_landed_state(self, state: int) -> None:
        """EXTENDED_SYS_STATE's ``landed_state``: no identification on the ground.

        An autopilot that never sends it (or sends UNDEFINED) leaves the
        collective as the only gate, as before."""
        if state != _LANDED_STATE_UNDEFINED:
            self.landed_state_seen = True
        on_ground = state == _LANDED_STATE_ON_GROUND
        if on_ground != self.controller.on_ground:
            self.controller.on_ground = on_ground
            self._mode_on_ground(on_ground)
            self._event("landed_state", "on the ground" if on_ground else f"in the air ({state})")

    def _on_highres_imu(self, v: tuple[Any, ...]) -> None:
        """HIGHRES_IMU ``(time_usec, xgyro, ygyro, zgyro)``, from the link's fast road."""
        if self._imu_source == "highres_imu":
            t_usec, g0, g1, g2 = v
            self._on_imu(t_usec * 1e-6, (g0, g1, g2))

    def _on_attitude(self, v: tuple[Any, ...]) -> None:
        """ATTITUDE ``(time_boot_ms, rollspeed, pitchspeed, yawspeed)``."""
        if self._imu_source == "attitude":
            t_ms, g0, g1, g2 = v
            self._on_imu(t_ms * 1e-3, (g0, g1, g2))

    def _on_imu(self, t_s: float, gyro: tuple[float, float, float]) -> None:
        # Everything before the command is what the sample needs: the timestamp and
        # range checks, the law, the send. Recording and the slower checks follow it.
        t0 = self.link.rx_perf_s  # the datagram's arrival
        t_prev = self._t_prev
        if t_prev is None:
            self._t_first = t_s
            dt = 0.0
        else:
            dt = t_s - t_prev
            if 0.0 < dt <= _STEP_AHEAD_S:
                dt = whole_us(dt)  # HIGHRES_IMU's stamps are whole us, ATTITUDE's ms
                if self._clock_candidate is not None:
                    self._clock_candidate = None  # the old clock goes on: it was one outlier
                    self.n_imu_time_outliers += 1
            else:  # late, a gap, a jump; also a NaN timestamp
                taken = self._on_time_anomaly(t_s, dt, t0)
                if taken is None:
                    return
                dt = taken
            if self._restart_dt:
                dt = 0.0
        self._restart_dt = False
        self._t_prev = t_s
        self.n_imu += 1
        try:
            self._step(t_s, dt, gyro, t0)
        except Exception:
            self._on_step_error()
            return
        self._errors_in_row = 0
        # The stale-IMU clock counts samples the law has processed, not samples seen.
        self._last_imu_wall = t0

    def _on_time_anomaly(self, t_s: float, dt: float, t_wall: float) -> float | None:
        """A sample whose time is not just after the last one's: the time step to
        fly it with, or None: dropped.

        A step back within ``_TIME_JUMP_S`` is a duplicate or a late sample
        (reordered on the link): dropped. A step forward that the wall clock
        also took, give or take ``_STEP_AHEAD_S`` (the datagrams' arrivals are
        as far apart as the stamps), is a gap in the stream: flown at once. Any
        other step may be one corrupt timestamp, and a sample whose time is
        unknown is not flown (the law would differentiate its rate over a time
        it may have faked; a NaN sample would stretch the invalid-IMU run): it
        is dropped and becomes a candidate. Only when ``_NEW_CLOCK_SAMPLES``
        samples in a row follow on from it is the jump real: forward, a gap
        after all (a lockstep simulator's clock outruns the wall's); backward,
        a new clock (the autopilot rebooted). A sample that follows the old
        clock again makes the candidate an outlier, and nothing changes: one
        forward stamp costs that one sample, a real gap the wall did not see
        two more.
        """
        if dt != dt or -_TIME_JUMP_S <= dt <= 0.0:
            self.n_imu_duplicate_or_late += 1
            return None
        # The step to fly a gap with: the law clamps it; beyond _TIME_JUMP_S it starts over.
        gap_dt = whole_us(dt) if dt <= _TIME_JUMP_S else 0.0
        last_wall = self._last_imu_wall
        cand = self._clock_candidate
        if dt > 0.0 and last_wall is not None and dt <= t_wall - last_wall + _STEP_AHEAD_S:
            self.n_imu_gaps += 1
            if cand is not None:
                self._clock_candidate = None
                self.n_imu_time_outliers += 1  # the old clock went on, through a gap
            return gap_dt
        if cand is not None and 0.0 < t_s - cand[0] <= _STEP_AHEAD_S:
            self._clock_candidate = (t_s, cand[1] + 1)
            if cand[1] + 1 < _NEW_CLOCK_SAMPLES:
                return None
            self._clock_candidate = None
            if dt > 0.0:
                self.n_imu_gaps += 1
                self._event("imu_gap", f"IMU time went on from {self._t_prev:.6f} s to {t_s:.6f} s")
                return gap_dt
            self._new_clock(t_s)
            return 0.0
        if cand is not None:
            self.n_imu_time_outliers += 1  # the previous candidate led nowhere
        self._clock_candidate = (t_s, 1)
        self.n_imu_time_jumps += 1
        return None

    def _new_clock(self, t_s: float) -> None:
        """The autopilot's IMU clock restarted (a reboot): start over.

        Engaged, it is a failsafe first (whatever made the clock jump, the
        vehicle was not ours to fly through it); then the controller forgets
        what it learnt, and the streams are asked for again (a rebooted
        autopilot has forgotten them)."""
        detail = f"IMU time jumped from {self._t_prev:.6f} s to {t_s:.6f} s"
        if self._t_first is not None and self._t_prev is not None:
            # Shadow mode's --duration counts sample time since the first sample: go on
            # counting on the new clock.
            self._t_first = t_s - (self._t_prev - self._t_first)
        if self.engaged or self.commanding:
            self._failsafe("failsafe_imu_clock", f"{detail} (autopilot reboot?)")
        self._reset_laws()
        self._forget_estimates()  # the rebooted estimator starts afresh
        self.watch.reset()
        self.watch.reset_invalid()
        self.n_imu_clock_resets += 1
        self._event("imu_clock_reset", detail)
        if self.stack is not None and not self._stop.is_set():
            self._spawn(self._rerequest_streams("IMU clock reset"), "streams")

    def _on_step_error(self) -> None:
        """The law, the send or the records raised on this sample: count it; a few
        in a row is a failsafe (nothing was sent for those samples)."""
        self.n_sample_errors += 1
        self._errors_in_row += 1
        if self.n_sample_errors == 1:
            _log.exception("the per-sample step raised (logged once, counted after)")
        limit = self.opts.failsafe.sample_errors_max
        if self._errors_in_row >= limit and (self.engaged or self.commanding):
            self._failsafe(
                "failsafe_sample_errors", f"the per-sample step raised {limit} times in a row"
            )

    def _step(self, t_s: float, dt: float, gyro: tuple[float, float, float], t0: float) -> None:
        """One accepted sample: the shared step (range gate, law, command gate), the
        command, then the rest."""
        if self.engaged and self._t_engaged is None:
            self._t_engaged = t_s  # engaged time counts from the first sample flown
        if self._duration_us is not None and not self._stop.is_set():
            # Engaged time; in shadow mode (never engaged) time since the first sample.
            since = self._t_engaged if self.opts.engage != "none" else self._t_first
            if since is not None and round((t_s - since) * 1e6) >= self._duration_us:
                # Stop commanding in this callback, before this sample's command: the
                # run flies [start, start + duration), whenever the run's task wakes.
                if self._release():
                    self._hand_back_owed = True  # the run's end hands back
                self._event("duration", f"{self._duration_s} s")
                self._stop.set()
        if self.tracking_the_vehicle:
            self._reset_laws()  # not flown yet: start from the vehicle's state (companion.modes)
        ref = self._ref  # mapped once per RC frame, in _on_rc
        thrust = self._thrust
        script = self._script
        if script is not None and self.engaged and self._t_engaged is not None:
            ref, scripted_thrust = script.at(t_s - self._t_engaged)
            if scripted_thrust is not None:
                thrust = scripted_thrust
        elif self.flight_mode != "rates":
            ref, thrust = self._mode_reference(dt, gyro, ref, thrust)
        step = self.step
        out = step.sample(dt, gyro, ref, thrust)
        if step.gyro_valid:
            self.watch.valid_sample(dt)
        else:
            self.n_imu_invalid += 1
            verdict = self.watch.invalid_sample(t_s, dt, engaged=self.engaged)
            if verdict is not None:
                self._failsafe(*verdict)
        sent: Sequence[float] = NO_RATES
        # As the command left (recorded so, whatever follows); in a flight mode, from
        # the first setpoint the autopilot flies (the laws' start: companion.modes).
        engaged = self.engaged or (self.needs_attitude and self.commanding and self.setpoints_flown)
        if self.commanding:
            sent = self._send_output(t_s, out, ref, thrust)
        else:
            self._applied_thrust = None  # the outer loops learn only what was sent
            self._rate_saturated = None
        t_sent = time.perf_counter()
        if self._mode_events:
            self._flush_mode_events()
        # ---- the command has left: what follows is off the latency path
        age = t_sent + self.link_clock.offset_s - t_s  # NaN until the first TIMESYNC answer
        self.sample_ages_s[self._n_ages % AGES_KEPT] = age
        self._n_ages += 1
        step.learn()
        gyro = step.gyro
        if self.engaged:
            verdict = self.watch.envelope(t_s, dt, gyro, out)
            if verdict is not None:
                self._failsafe(*verdict)
        append = self._log_append
        if append is not None:
            tq = out.torque
            err = out.error
            f_hat = out.f_hat
            u = out.u
            sat = out.saturated_axes
            g0, g1, g2 = gyro
            # The layout of companion.records.columns.
            append(
                [
                    t_s, t0, (t_sent - t0) * 1e6, float(engaged), float(out.held),
                    ref[0], g0, err[0], f_hat[0], u[0], tq[0], float(sat[0]),
                    ref[1], g1, err[1], f_hat[1], u[1], tq[1], float(sat[1]),
                    ref[2], g2, err[2], f_hat[2], u[2], tq[2], float(sat[2]),
                    thrust, out.thrust, *out.motors, *sent, float(self.controller.on_ground),
                    self.link_clock.rtt_s * 1e3, age * 1e3, *self._mode_log(),
                    *(step.law_ref if step.shaper is not None else NO_RATES),
                ]
            )  # fmt: skip
        if self._telemetry is not None:
            self._telemetry.publish_sample(t_s, out.error, out.f_hat, out.u)

    def _send_output(
        self, t_s: float, out: Any, ref: tuple[float, float, float], thrust: float
    ) -> Sequence[float]:
        """Send this sample's command through the last gate; returns the body rates
        sent (NaN: none)."""
        if self._actuator_output:
            controls, replaced = self.step.actuator_command(out, thrust)
            if replaced:
                self._gated(replaced)
            r, p, y, t = controls
            self.link.send_actuator_controls(round(t_s * 1e6), (r, p, y, t, 0.0, 0.0, 0.0, 0.0))
            self._applied_thrust = t
            self._rate_saturated = out.saturated_axes
            self.n_commands += 1
            return NO_RATES
        sp, thrust_out, replaced = self.step.rates_command(out, ref, thrust)
        if replaced:
            self._gated(replaced)
        self.link.send_body_rates(round(t_s * 1e3) & 0xFFFFFFFF, sp, thrust_out)
        self._applied_thrust = thrust_out
        self._rate_saturated = None  # the autopilot's rate loop: its mixer is not seen
        self.n_commands += 1
        return sp

    def _gated(self, n: int) -> None:
        """The last gate replaced ``n`` non-finite fields of a command."""
        self.n_commands_gated += n
        if self.n_commands_gated == n:
            self._event("command_gated", f"{n} non-finite field(s) replaced by safe values")

    def _on_rc(self, v: tuple[int, ...]) -> None:
        """RC_CHANNELS ``(chan1_raw, ..., chan18_raw, chancount)``: the pilot's radio,
        while the autopilot reports its receiver healthy."""
        if not self._rc_receiver_healthy:
            self.n_rc_unhealthy += 1
            return
        count = v[18]
        chans = v[: min(count, 18)] if count else v[:18]
        if self._on_pilot(chans):
            self._rc_radio_wall = self._rc_wall

    def _on_manual_control(self, v: tuple[int, ...]) -> None:
        """MANUAL_CONTROL ``(x, y, z, r, enabled_extensions, aux1, ..., aux6)``: the
        pilot's joystick as the autopilot streams it (PX4 without a radio: a ground
        station's joystick). Used only while no valid RC_CHANNELS frame came within
        the RC timeout: a radio, where there is one, is the pilot's input."""
        now = time.perf_counter()
        timeout = self.opts.failsafe.rc_timeout_s
        last, self._joystick_wall = self._joystick_wall, now
        if last is None or now - last > timeout:
            # PX4 answers the stream's request with one frame at once, a ground
            # station's joystick or not: a joystick is a stream, from its second frame.
            return
        radio = self._rc_radio_wall
        if radio is not None and now - radio <= timeout:
            return
        self._on_pilot(joystick_channels(v, self.sticks.channels))

    def _on_pilot(self, chans: Sequence[int]) -> bool:
        """The pilot's channels (us, index 0 = ch1), from either input; whether valid."""
        cmd = self.sticks.map(chans)
        if not cmd.valid:
            # A glitch (a channel missing or out of range) changes nothing: the last
            # valid sticks and switch hold, as PX4 and ArduPilot hold theirs, until
            # the RC-lost failsafe (which watches _rc_wall) says otherwise.
            self.n_rc_invalid += 1
            return False
        self._rc = tuple(chans)
        self._ref, self._thrust, self._deflection = cmd.rate_rad_s, cmd.thrust, cmd.deflection
        self._rc_wall = time.perf_counter()
        self._switch(chans)
        return True

    def _switch(self, chans: Sequence[int]) -> None:
        """The engage switch, on each valid frame of the pilot's input."""
        if self.opts.engage != "rc-switch" or not self.started_up:
            return
        ch = self.opts.engage_channel
        value = chans[ch - 1] if ch <= len(chans) else 0
        high = 1700 <= value <= 2200
        if not self._switch_seen_low:
            if not high:
                self._switch_seen_low = True
            elif not self._switch_said_high:
                self._switch_said_high = True
                self._event(
                    "rc_switch_high_at_start",
                    f"ch{ch} high ({value} us) at start: nothing engages until the "
                    "switch has been low; put it low, then high to engage",
                )
            return
        if not self._switch_high and high:
            self._switch_high = True
            self._event("rc_switch", f"ch{ch} high ({value} us): engaging")
            self._start_engage(arm=False)
        elif self._switch_high and (value < 1300 or value > 2200):
            self._switch_high = False
            task = self._engage_task
            if task is not None and not task.done() and not self.commanding:
                # Still waiting for the flight mode's estimates: nothing was sent yet.
                task.cancel()
                self._event("rc_switch", f"ch{ch} low ({value} us): engagement abandoned")
            if self.engaged or self.commanding:
                was = self._release()
                self._event("rc_switch", f"ch{ch} low ({value} us): handing back")
                self._spawn(self._hand_back("pilot switched back", was_commanding=was), "hand-back")

    def _on_heartbeat(self, msg: Any) -> None:
        mode = int(msg.custom_mode)
        armed = bool(msg.base_mode & _BASE_MODE_ARMED)
        status = int(msg.system_status)
        if status != self._ap_status and self._ap_status is not None:
            if status in _FAILSAFE_STATES:
                self._event("autopilot_failsafe", f"system status {_STATE_NAMES[status]}")
            elif self._ap_status in _FAILSAFE_STATES:
                self._event("autopilot_failsafe_cleared", f"system status {status}")
        self._ap_status = status
        if self.stack is None:
            # Not yet recognised (start-up): only what it flies, for an engagement
            # that follows at once (the mode it began from).
            self._ap_mode, self._ap_armed = mode, armed
            return
        offboard = self.stack.is_engage_mode(mode)
        was = self.engaged
        now = offboard and armed and self.commanding
        self._ap_mode, self._ap_armed = mode, armed
        self._ap_heartbeats += 1
        if now and not was and not self._stop.is_set():
            # (After a stop signal nothing engages: the run's hand-back is next.)
            if not (self.needs_attitude and self.setpoints_flown):
                # Learn F only from commands that are applied. A flight mode's laws
                # started when the engage mode was accepted (companion.modes): they
                # run on, or the vehicle would jolt a second time.
                self._reset_laws()
                self._restart_dt = True  # the next sample primes it, as a replay does
            self.setpoints_flown = True
            self.watch.reset()
            self.engaged = True
            self._t_engaged = None  # set by the first sample flown
            label = self.stack.mode_label(mode)
            self._event("engaged", f"{label} and armed at t={self._t_prev}")
        elif was and not now and not self._handing_back:
            self.engaged = False
            self._failsafe(
                "failsafe_autopilot_took_over",
                f"autopilot left {self.stack.engage_label} for {self.stack.mode_label(mode)}"
                f" (mode {mode:#x}, armed={armed})",
            )
