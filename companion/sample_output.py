"""What leaves for each IMU sample, and what is kept of it.

The flight core (:class:`companion.core.FlightCore`) owns one. :meth:`send`:
the sample's command through the last gate (:class:`companion.step.SampleStep`'s
actuator or rates command) to the shell that puts it on the wire, and what the
flight mode's loops learn of it (the collective sent, our mixer's saturation).
:meth:`keep`, off the latency path: the sample's age when its command left (a
ring of the last :data:`AGES_KEPT`, for the link's figures), its control-log row
(the layout of :func:`companion.records.columns`) and its telemetry. No I/O of
its own: the shell's send, and the sinks it is given.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from companion.control import RateController
from companion.link.timesync import LinkClock
from companion.modes import ModeLaws
from companion.shell import Shell
from companion.step import NO_RATES, SampleStep

__all__ = ["AGES_KEPT", "SampleOutput"]

AGES_KEPT = 1024
"""The last samples' ages kept for the link's figures (about 1 s at 1 kHz)."""

Vec3 = tuple[float, float, float]


class SampleOutput:
    """One run's per-sample output (module docstring).

    Parameters
    ----------
    shell
        What sends the commands and records the events.
    step, controller, modes
        The run's shared step, rate law and flight mode (read for the record).
    link_clock
        The link's measured clock (the sample's age).
    actuator
        Actuator controls go out (``--output actuator``); else body rates.
    """

    def __init__(
        self,
        shell: Shell,
        step: SampleStep,
        controller: RateController,
        modes: ModeLaws,
        link_clock: LinkClock,
        *,
        actuator: bool,
    ) -> None:
        self.shell = shell
        self.step = step
        self.controller = controller
        self.modes = modes
        self.link_clock = link_clock
        self.actuator = actuator
        self.sample_ages_s = [float("nan")] * AGES_KEPT
        self.n_ages = 0
        self.log_append: Callable[[list[float]], None] | None = None
        """Where each sample's control-log row goes (None: not recorded)."""
        self.publish_sample: Callable[..., None] | None = None
        """Where each sample's telemetry goes (None: none)."""
        self.n_commands = 0
        self.n_commands_gated = 0

    def send(self, t_s: float, out: Any, ref: Vec3, thrust: float) -> Sequence[float]:
        """Send this sample's command through the last gate; returns the body rates
        sent (NaN: none)."""
        modes = self.modes
        if self.actuator:
            controls, replaced = self.step.actuator_command(out, thrust)
            if replaced:
                self._gated(replaced)
            r, p, y, t = controls
            self.shell.send_actuator_controls(round(t_s * 1e6), (r, p, y, t, 0.0, 0.0, 0.0, 0.0))
            modes.applied_thrust = t
            modes.rate_saturated = out.saturated_axes
            self.n_commands += 1
            return NO_RATES
        sp, thrust_out, replaced = self.step.rates_command(out, ref, thrust)
        if replaced:
            self._gated(replaced)
        self.shell.send_body_rates(round(t_s * 1e3) & 0xFFFFFFFF, sp, thrust_out)
        modes.applied_thrust = thrust_out
        modes.rate_saturated = None  # the autopilot's rate loop: its mixer is not seen
        self.n_commands += 1
        return sp

    def _gated(self, n: int) -> None:
        """The last gate replaced ``n`` non-finite fields of a command."""
        self.n_commands_gated += n
        if self.n_commands_gated == n:
            self.shell.event("command_gated", f"{n} non-finite field(s) replaced by safe values")

    def age(self, t_s: float, t_sent: float) -> float:
        """The sample's age when its command left, kept in the ring (NaN until the
        first TIMESYNC answer)."""
        age = t_sent + self.link_clock.offset_s - t_s
        self.sample_ages_s[self.n_ages % AGES_KEPT] = age
        self.n_ages += 1
        return age

    def keep(
        self,
        t_s: float,
        t0: float,
        t_sent: float,
        age: float,
        engaged: bool,
        out: Any,
        ref: Vec3,
        thrust: float,
        sent: Sequence[float],
    ) -> None:
        """The sample's control-log row and telemetry (``t0``: when it arrived,
        ``t_sent``: when its command left; ``engaged`` as it left)."""
        append = self.log_append
        if append is not None:
            step = self.step
            tq = out.torque
            err = out.error
            f_hat = out.f_hat
            u = out.u
            sat = out.saturated_axes
            g0, g1, g2 = step.gyro
            alpha, lag, delay = self.controller.identified()
            # The layout of companion.records.columns.
            append(
                [
                    t_s, t0, (t_sent - t0) * 1e6, float(engaged), float(out.held),
                    ref[0], g0, err[0], f_hat[0], u[0], tq[0], float(sat[0]),
                    ref[1], g1, err[1], f_hat[1], u[1], tq[1], float(sat[1]),
                    ref[2], g2, err[2], f_hat[2], u[2], tq[2], float(sat[2]),
                    thrust, out.thrust, *out.motors, *sent, float(self.controller.on_ground),
                    self.link_clock.rtt_s * 1e3, age * 1e3, *self.modes.log_columns(),
                    *(step.law_ref if step.shaper is not None else NO_RATES),
                    *alpha, *lag, *delay, self.controller.yaw_share.value,
                ]
            )  # fmt: skip
        if self.publish_sample is not None:
            self.publish_sample(t_s, out.error, out.f_hat, out.u)
