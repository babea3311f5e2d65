"""The flight core: what arrived from the autopilot and the pilot, to what to do.

One synchronous object per run, with no I/O, no asyncio and no clock of its
own: it is given each message as it arrives (an IMU sample, the pilot's frame,
a heartbeat, an estimate) with the time it arrived, and it answers through the
:class:`Shell` that runs it: the command for each sample, the events, and the
requests only the shell can carry out (engage, hand back, ask for the streams
again, stop). ``companion run`` is one such shell (:mod:`companion.app`, over
MAVLink); the lab flies the same core in process.

Per IMU sample, inside the shell's receive callback, with no queue and no task
switch: the timestamp checks (:class:`companion.imu_time.ImuTimeline`), the
flight mode's reference (:class:`companion.modes.ModeLaws`), the shared step
(:class:`companion.step.SampleStep`: gyro range gate, law, command gate), the
command; then, off the latency path, what the law learns, the failsafes judged
per sample (:class:`companion.failsafe.SampleWatch`) and the record. The
pilot's frames (:class:`companion.pilot.PilotInput`) carry the reference and
the engage switch; the autopilot's heartbeats say whether the vehicle is
engaged, and its other messages go where they are kept
(:class:`companion.autopilot_messages.AutopilotMessages`).

Engaged means the autopilot's heartbeat shows the engage mode (OFFBOARD,
GUIDED_NOGPS) and armed while we command; a failsafe stops the commands in the
call that finds it (:meth:`FlightCore.failsafe`), before the shell hands back.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

from companion.autopilot_messages import AutopilotMessages
from companion.autopilot_state import AutopilotState
from companion.config import build_controller, build_stick_map
from companion.control import RateController
from companion.control.outer import OuterLaw
from companion.failsafe import SampleWatch
from companion.flight_modes import FLIGHT_MODES
from companion.handback import Conditions, failsafe_state
from companion.imu_time import NEW_CLOCK, ImuTimeline
from companion.link.timesync import LinkClock
from companion.modes import ModeLaws
from companion.pilot import EngageSwitch, PilotInput
from companion.run_options import RunOptions
from companion.sample_output import SampleOutput
from companion.shell import Shell
from companion.stacks import FlightStack
from companion.step import NO_RATES, SampleStep

__all__ = ["FlightCore", "Shell"]

_log = logging.getLogger("companion.app")


class FlightCore:
    """One run's decisions (module docstring).

    Parameters
    ----------
    opts
        The run's options.
    shell
        What runs the core.
    clock
        The shell's clock, s (read when a command leaves and a frame arrives).
    controller
        The rate law to fly instead of the one ``opts.controller`` builds (the
        lab's oracle).
    outer_law
        Makes the outer loops to fly in the altitude and position modes instead
        of their own (the lab's baseline, PX4's default cascade).
    """

    def __init__(
        self,
        opts: RunOptions,
        shell: Shell,
        clock: Callable[[], float],
        *,
        controller: RateController | None = None,
        outer_law: Callable[[], OuterLaw] | None = None,
    ) -> None:
        self.opts = opts
        self.shell = shell
        self.clock = clock
        self.controller = controller or build_controller(opts.controller, opts.profile)
        FLIGHT_MODES[opts.mode].fit(self.controller)
        self.pilot = PilotInput(build_stick_map(opts.controller), opts.failsafe.rc_timeout_s)
        # The range gate, the law and the command gate: the lab's flights use the same.
        self.step = SampleStep(
            self.controller,
            opts.profile,
            output=opts.output,
            rates_full_scale_deg_s=opts.rates_full_scale_deg_s,
            rates_lead_s=opts.rates_lead_s,
            rates_passthrough=opts.rates_passthrough,
            rates_law_axes=opts.rates_law_axes,
        )
        # The failsafes judged on each sample (in sample time).
        self.watch = SampleWatch(
            opts.failsafe,
            self.step.rate_max_rad_s,
            opts.profile.limits.motor_idle,
            actuator=opts.output == "actuator",
        )
        self.modes = ModeLaws(
            FLIGHT_MODES[opts.mode],
            opts.mission,
            stale_estimate_s=opts.failsafe.stale_estimate_s,
            stale_position_s=opts.failsafe.stale_position_s,
            outer_law=outer_law,
        )
        self.time = ImuTimeline()
        self.stack: FlightStack | None = None
        """The autopilot's flight stack, once the shell has recognised it."""
        self.imu_source = opts.imu_source
        self.engaged = False
        self.commanding = False
        """Setpoints are being sent."""
        self.setpoints_flown = False
        """The autopilot flies our setpoints (it accepted the engage mode, and the
        arming if asked); until then, commanding, the flight modes' laws track
        the vehicle (:mod:`companion.modes`)."""
        self.handing_back = False
        self.in_failsafe = False
        self.started_up = False
        """Start-up is over (the stack recognised, the streams requested): the
        switch is read from then on."""
        self.mode_before_engaging: int | None = None
        """The autopilot's ``custom_mode`` as the last engagement began."""
        self.ap = AutopilotState()
        """What the autopilot says of itself."""
        self.switch = EngageSwitch(opts.engage_channel)
        self.t_engaged: float | None = None
        self._script = opts.reference
        # Counted in the autopilot's whole microseconds: a float difference of two
        # large stamps would end the run one sample early or late by its rounding.
        self._duration_us = None if opts.duration_s is None else round(opts.duration_s * 1e6)
        # The law takes something from RC (the sticks, the throttle, the engage
        # switch) unless a reference file with its own collective flies it.
        self.rc_needed = (
            opts.engage == "rc-switch" or opts.reference is None or opts.reference.thrust is None
        )
        # The link, measured: TIMESYNC round trips (the shell asks), and each
        # sample's age when its command leaves (the output keeps it).
        self.link_clock = LinkClock()
        self.output = SampleOutput(
            shell, self.step, self.controller, self.modes, self.link_clock,
            actuator=opts.output == "actuator",
        )  # fmt: skip
        """What leaves for each sample, and what is kept of it (its record's sinks)."""
        self.messages = AutopilotMessages(
            shell, clock, self.on_heartbeat, ap=self.ap, pilot=self.pilot, modes=self.modes,
            controller=self.controller, link_clock=self.link_clock,
        )  # fmt: skip
        """The autopilot's other messages, each to what keeps it (HEARTBEAT: here)."""
        self.n_imu = 0
        self.n_imu_invalid = 0
        self.n_imu_clock_resets = 0
        self.n_sample_errors = 0
        self._errors_in_row = 0

    # ------------------------------------------------------------------ state
    @property
    def needs_attitude(self) -> bool:
        return self.modes.needs_attitude

    @property
    def needs_position(self) -> bool:
        return self.modes.needs_position

    @property
    def tracking_the_vehicle(self) -> bool:
        """Commanding, in a flight mode, and the autopilot not flying our setpoints
        yet: the laws start again from the vehicle's state each sample."""
        return self.modes.needs_attitude and self.commanding and not self.setpoints_flown

    def counters(self) -> dict[str, int]:
        t, p, m = self.time, self.pilot, self.modes
        return {
            "imu_samples": self.n_imu,
            "imu_duplicate_or_late": t.n_duplicate_or_late,
            "imu_invalid": self.n_imu_invalid,
            "imu_time_jumps": t.n_time_jumps,
            "imu_gaps": t.n_gaps,
            "imu_time_outliers": t.n_time_outliers,
            "imu_clock_resets": self.n_imu_clock_resets,
            "commands_sent": self.output.n_commands,
            "commands_gated": self.output.n_commands_gated,
            "sample_errors": self.n_sample_errors,
            "rc_invalid": p.n_invalid,
            "rc_unhealthy": p.n_unhealthy,
            "estimate_invalid": m.n_estimate_invalid,
            "position_invalid": m.n_position_invalid,
        }

    def conditions(self, now: float, *, rc_failsafe: bool) -> Conditions:
        """What a safe mode may be chosen on, now."""
        return Conditions(
            # Frames that came while the receiver was healthy, and it still is (ArduPilot
            # streams a lost radio's last pulses; its SYS_STATUS says it is lost).
            rc_valid=self.pilot.valid_rc(now),
            position_valid=self.messages.position_valid(now),
            rc_failsafe=rc_failsafe,
            autopilot_failsafe=failsafe_state(self.ap.status),
        )

    def not_ready_to_engage(self, now: float) -> str | None:
        """Why the vehicle must not be engaged now, or None."""
        why = self.modes.not_ready()
        if why is not None:
            return why
        if self.opts.engage == "auto" and self.rc_needed and not self.pilot.fresh(now):
            # (With rc-switch the pilot's switch, in their own input, is the engagement.)
            return (
                "no valid pilot input (RC_CHANNELS, or MANUAL_CONTROL from a joystick) "
                "yet: the sticks fly"
            )
        return self.modes.estimates_missing()

    def in_engage_mode(self) -> bool:
        """The autopilot's last heartbeat showed the mode we engage in."""
        return (
            self.stack is not None
            and self.ap.mode is not None
            and self.stack.is_engage_mode(self.ap.mode)
        )

    # ------------------------------------------------------- engaging, failsafes
    def begin_commanding(self) -> None:
        """An engagement starts streaming setpoints (the autopilot does not fly
        them until it accepts the engage mode)."""
        self.mode_before_engaging = self.ap.mode
        self.setpoints_flown = False
        self.t_engaged = None  # set by the first sample flown
        self.commanding = True
        self.reset_laws()

    def setpoints_now_flown(self) -> None:
        """The autopilot accepted the engage mode (and the arming, if asked): from
        the next sample it flies our setpoints, so the laws start here, in every
        mode (a flight mode's from the vehicle's state: :mod:`companion.modes`),
        and learn only from commands that are flown. The heartbeat that shows the
        mode (the engaged edge, :meth:`on_heartbeat`) may come up to a second
        later: PX4 sends one a second (ArduCopter one at once on a mode change)."""
        if not self.commanding or self.setpoints_flown:
            return
        self.reset_laws()  # before the flag: a flight mode takes over the autopilot's collective
        self.time.restart = True
        self.setpoints_flown = True

    def release(self) -> bool:
        """Stop commanding now, in the caller's call; return whether we were.

        Called the moment a failsafe or the pilot's switch says so, so no later
        sample (even one in the same datagram) gets a command, and an engagement
        still under way is abandoned rather than switching the autopilot back."""
        was = self.commanding
        self.commanding = False
        self.engaged = False
        self.setpoints_flown = False
        self.shell.cancel_engaging()
        return was

    def failsafe(self, kind: str, detail: str) -> None:
        """Stop commanding now and have the shell hand back; record it afterwards.

        The commands stop in this call, the hand-back is asked for before the
        event is recorded, and recording never raises."""
        if self.shell.stopping or self.in_failsafe:
            return  # one failsafe at a time: the first reason is the one logged
        self.in_failsafe = True
        was = self.release()
        self.shell.after_failsafe(kind, detail, was_commanding=was)
        self.shell.event(kind, detail)

    def failsafe_over(self) -> None:
        """The shell's hand-back after a failsafe is done."""
        self.in_failsafe = False

    def reset_laws(self) -> None:
        """Forget what the laws learnt: the rate law and the flight mode's loops."""
        self.controller.reset()
        self.step.reset()
        self._reset_modes(self.pilot.thrust)

    def _reset_modes(self, pilot_thrust: float) -> None:
        modes = self.modes
        if not modes.built:
            return
        on_ground = bool(self.controller.on_ground)
        stack, before = self.stack, self.mode_before_engaging
        manual = stack is not None and before is not None and before in stack.throttle_modes
        take_over = modes.take_over_thrust(
            pilot_thrust, self.clock(), flown=self.setpoints_flown, manual_before=manual
        )
        modes.reset(take_over, on_ground=on_ground)

    # --------------------------------------------------------------- messages
    def on_heartbeat(self, msg: Any) -> None:
        """HEARTBEAT: the autopilot's mode, armed state and failsafe state; the engaged edge."""
        ap = self.ap
        change = ap.heartbeat(msg)
        if change is not None:
            self.shell.event(*change)
        stack = self.stack
        if stack is None:
            return  # not yet recognised (start-up): only what it flies, kept
        mode, armed = ap.mode, ap.armed
        assert mode is not None
        was = self.engaged
        now = stack.is_engage_mode(mode) and armed and self.commanding
        ap.heartbeats += 1
        if now and not was and not self.shell.stopping:
            # (After a stop nothing engages: the run's hand-back is next.)
            if not self.setpoints_flown:
                # Learn F only from commands that are applied. Where the engage mode's
                # acceptance came first, the laws started there (setpoints_now_flown):
                # they run on, or the vehicle would jolt a second time.
                self.reset_laws()
                self.time.restart = True  # the next sample primes it, as a replay does
            self.setpoints_flown = True
            self.watch.reset()
            self.engaged = True
            self.shell.event(
                "engaged", f"{stack.mode_label(mode)} and armed at t={self.time.t_prev}"
            )
        elif was and not now and not self.handing_back:
            self.engaged = False
            self.failsafe(
                "failsafe_autopilot_took_over",
                f"autopilot left {stack.engage_label} for {stack.mode_label(mode)}"
                f" (mode {mode:#x}, armed={armed})",
            )

    def on_rc(self, v: Sequence[Any], now: float) -> None:
        """RC_CHANNELS ``(chan1_raw, ..., chan18_raw, chancount)``."""
        chans = self.pilot.from_radio(v, now)
        if chans is not None:
            self._switch(chans)

    def on_manual_control(self, v: Sequence[Any], now: float) -> None:
        """MANUAL_CONTROL ``(x, y, z, r, enabled_extensions, aux1, ..., aux6)``."""
        chans = self.pilot.from_joystick(v, now)
        if chans is not None:
            self._switch(chans)

    def _switch(self, chans: Sequence[int]) -> None:
        """The engage switch, on each valid frame of the pilot's input."""
        if self.opts.engage == "rc-switch" and self.started_up:
            self.switch.on_frame(
                chans, self.shell, engaged=self.engaged, commanding=self.commanding,
                release=self.release,
            )  # fmt: skip

    # ------------------------------------------------------------ the samples
    def on_imu(self, t_s: float, gyro: tuple[float, float, float], arrival: float) -> None:
        """One IMU sample stamped ``t_s`` that arrived at ``arrival``: everything
        before the command is what the sample needs (the timestamp and range
        checks, the law, the send); recording and the slower checks follow it."""
        tl = self.time
        dt = tl.step_of(t_s, arrival)
        if dt is None:
            return
        if tl.gap_detail is not None:
            self.shell.event("imu_gap", tl.gap_detail)
            tl.gap_detail = None
        if dt == NEW_CLOCK:
            self._new_clock(t_s)
            dt = 0.0
        tl.advance(t_s)
        self.n_imu += 1
        try:
            self._step(t_s, dt, gyro, arrival)
        except Exception:
            self._on_step_error()
            return
        self._errors_in_row = 0
        # The stale-IMU clock counts samples the law has processed, not samples seen.
        tl.last_arrival = arrival

    def imu_stale(self, now: float, limit_s: float) -> bool:
        """No sample processed for ``limit_s`` (once one has been)."""
        last = self.time.last_arrival
        return last is not None and now - last > limit_s

    def _new_clock(self, t_s: float) -> None:
        """The autopilot's IMU clock restarted (a reboot): start over.

        Engaged, it is a failsafe first (whatever made the clock jump, the
        vehicle was not ours to fly through it); then the controller forgets
        what it learnt, and the streams are asked for again (a rebooted
        autopilot has forgotten them)."""
        detail = self.time.new_clock(t_s)
        if self.engaged or self.commanding:
            self.failsafe("failsafe_imu_clock", f"{detail} (autopilot reboot?)")
        self.reset_laws()
        self.modes.forget_estimates()  # the rebooted estimator starts afresh
        self.watch.reset()
        self.watch.reset_invalid()
        self.n_imu_clock_resets += 1
        self.shell.event("imu_clock_reset", detail)
        if self.stack is not None and not self.shell.stopping:
            self.shell.rerequest_streams("IMU clock reset")

    def _on_step_error(self) -> None:
        """The law, the send or the records raised on this sample: count it; a few
        in a row is a failsafe (nothing was sent for those samples)."""
        self.n_sample_errors += 1
        self._errors_in_row += 1
        if self.n_sample_errors == 1:
            _log.exception("the per-sample step raised (logged once, counted after)")
        limit = self.opts.failsafe.sample_errors_max
        if self._errors_in_row >= limit and (self.engaged or self.commanding):
            self.failsafe(
                "failsafe_sample_errors", f"the per-sample step raised {limit} times in a row"
            )

    def _step(self, t_s: float, dt: float, gyro: tuple[float, float, float], t0: float) -> None:
        """One accepted sample: the shared step (range gate, law, command gate), the
        command, then the rest."""
        flown = self.commanding and self.setpoints_flown
        if flown and self.t_engaged is None:
            self.t_engaged = t_s  # engaged time counts from the first sample flown
        shell = self.shell
        if self._duration_us is not None and not shell.stopping:
            # Engaged time; in shadow mode (never engaged) time since the first sample.
            since = self.t_engaged if self.opts.engage != "none" else self.time.t_first
            if since is not None and round((t_s - since) * 1e6) >= self._duration_us:
                # Stop commanding in this call, before this sample's command: the
                # run flies [start, start + duration), whenever the shell acts on it.
                owed = self.release()  # the run's end hands back
                shell.event("duration", f"{self.opts.duration_s} s")
                shell.stop(hand_back_owed=owed)
        if self.tracking_the_vehicle:
            self.reset_laws()  # not flown yet: start from the vehicle's state (companion.modes)
        pilot = self.pilot
        ref = pilot.rate_rad_s  # mapped once per frame of the pilot's
        thrust = pilot.thrust
        script = self._script
        modes = self.modes
        since_s = self.t_engaged if self.commanding and self.setpoints_flown else None
        if script is not None and since_s is not None:
            ref, scripted_thrust = script.at(t_s - since_s)
            if scripted_thrust is not None:
                thrust = scripted_thrust
        elif modes.needs_attitude:
            ref, thrust = self._mode_reference(dt, gyro, ref, thrust)
        step = self.step
        out = step.sample(dt, gyro, ref, thrust)
        if step.gyro_valid:
            self.watch.valid_sample(dt)
        else:
            self.n_imu_invalid += 1
            verdict = self.watch.invalid_sample(t_s, dt, engaged=self.engaged)
            if verdict is not None:
                self.failsafe(*verdict)
        sent: Sequence[float] = NO_RATES
        # As the command left (recorded so, whatever follows); from the first setpoint
        # the autopilot flies (the laws' start: setpoints_now_flown).
        engaged = self.engaged or (self.commanding and self.setpoints_flown)
        if self.commanding:
            sent = self.output.send(t_s, out, ref, thrust)
        else:
            modes.applied_thrust = None  # the outer loops learn only what was sent
            modes.rate_saturated = None
        t_sent = self.clock()
        if modes.events:
            for kind, detail in modes.events:
                shell.event(kind, detail)
            modes.events.clear()
        # ---- the command has left: what follows is off the latency path
        age = self.output.age(t_s, t_sent)
        step.learn()
        if self.engaged:
            verdict = self.watch.envelope(t_s, dt, step.gyro, out)
            if verdict is not None:
                self.failsafe(*verdict)
        self.output.keep(t_s, t0, t_sent, age, engaged, out, ref, thrust, sent)

    def _mode_reference(
        self, dt: float, gyro: tuple[float, float, float], ref: Any, thrust: float
    ) -> tuple[Any, float]:
        """This sample's rate reference and collective in the flight mode (``ref`` and
        ``thrust``: the pilot's). Without fresh estimates: no rates and the pilot's
        collective (the rate loop holds the attitude it has), and, engaged, a
        failsafe first."""
        modes = self.modes
        stale = modes.age_estimates(dt)
        if stale is not None:
            if self.engaged or self.commanding:
                self.failsafe(*stale)
            self._reset_modes(thrust)
            return (0.0, 0.0, 0.0), thrust
        return modes.sample_reference(
            dt, gyro, ref, thrust, self.pilot.deflection, self.controller,
            gyro_limit_rad_s=self.step.gyro_limit_rad_s, mission_flown=self.engaged,
        )  # fmt: skip
