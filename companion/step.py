"""One IMU sample in, one command out: the step ``companion run`` and the lab's flights share.

Per sample, in this order:

1. the gyro range gate: a sample beyond the sensor's full scale (5 % over, for
   its own overshoot), or not finite, is not a measurement; the law is given
   NaN and holds its last output, and the next valid sample's step counts
   from the last sample the law flew;
2. the law (the controller's ``update``);
3. the last gate on the command: actuator controls, or body rates composed
   from the pilot's rate and the law's correction within the profile's limits.

No I/O and no clock. The caller sends the command, then calls :meth:`learn`
off the latency path; what the failsafes make of an invalid sample is the
caller's (:attr:`SampleStep.gyro_valid` says which it was).
"""

from __future__ import annotations

import math
from typing import Any

from companion.control import AXES, RateController
from companion.control.gate import gate_actuator, gate_rates
from companion.control.shaping import RateShaper
from companion.profile import VehicleProfile
from companion.rate_loop import ALL_AXES, LawAxes

__all__ = [
    "LANDED_STATE_RATE_HZ",
    "NO_RATES",
    "SampleStep",
    "law_axes_named",
    "law_axes_names",
    "law_share",
    "whole_us",
]

NO_RATES = (math.nan, math.nan, math.nan)
"""The body rates of a sample that sent none (actuator output, or not commanding)."""

LANDED_STATE_RATE_HZ = 4.0
"""The rate the companion asks for the autopilot's landed state (no identification
on the ground: the law's ``on_ground``)."""

GYRO_RANGE_MARGIN = 1.05
"""How far past its full scale a gyro may read and still be a measurement."""


def whole_us(dt: float) -> float:
    """A positive time step rounded to whole microseconds.

    The stamps are whole microseconds (or milliseconds): rounded, the step does
    not carry the rounding of two large floats, so a flight does not depend on
    when (in the autopilot's clock) it began. A step that rounds to nothing is
    left as it is."""
    us = round(dt * 1e6)
    return us * 1e-6 if us > 0 else dt


def law_share(torque: Any, axes: LawAxes) -> tuple[float, float, float]:
    """The law's normalised correction on the axes it corrects, 0 on the others."""
    t0, t1, t2 = torque
    return (t0 if axes[0] else 0.0, t1 if axes[1] else 0.0, t2 if axes[2] else 0.0)


def law_axes_named(names: str) -> LawAxes:
    """Per axis, whether ``names`` (``--rates-law-axes``: a comma-separated set of
    roll, pitch and yaw, each once) holds it.

    Raises
    ------
    ValueError
        If a name is not an axis or is given twice.
    """
    given = [v.strip() for v in names.split(",")]
    if any(n not in AXES for n in given) or len(set(given)) != len(given):
        raise ValueError(
            f"expected a comma-separated set of {', '.join(AXES)} (each once), got {names!r}"
        )
    return (AXES[0] in given, AXES[1] in given, AXES[2] in given)


def law_axes_names(axes: LawAxes) -> str:
    """The ``--rates-law-axes`` value for ``axes`` (the inverse of :func:`law_axes_named`)."""
    return ",".join(a for a, on in zip(AXES, axes, strict=True) if on)


def _unit(x: float) -> float:
    """``x`` within [-1, 1] (a normalised torque)."""
    return 1.0 if x > 1.0 else -1.0 if x < -1.0 else x


class SampleStep:
    """The gyro range gate, the law and the command gate, for one controller.

    Parameters
    ----------
    controller
        The law.
    profile
        The vehicle: its gyro range and its rate limits.
    output
        ``"actuator"`` (normalised torques and collective) or ``"rates"``
        (body rates and collective, for the autopilot's own rate loop).
    rates_full_scale_deg_s
        Rates output: the rate a full-scale law output stands for (default:
        the profile's rate limits).
    rates_lead_s
        Rates output: how far ahead of the pilot's rate the setpoint leads
        (the reference's derivative times this).
    rates_passthrough
        Rates output: send the pilot's rate alone (the law still runs).
    rates_law_axes
        Rates output: per axis (roll, pitch, yaw), whether the law's correction
        is added; an axis without it is sent the pilot's rate and the lead, and
        its law is taught that nothing of its output was applied. None: all
        three, until :meth:`set_law_axes` chooses.
    rate_accel_max_rad_s2
        Rates output: the autopilot's acceleration limits on a body-rate
        setpoint (ArduCopter's input shaping, :mod:`companion.control.shaping`),
        or None where it flies the setpoint as sent (PX4). With them the law
        flies the shaped reference, the setpoint sent respects the limits and
        stays within what they bring in over a short horizon of that reference,
        and the law is taught what was sent; the lead is off (the autopilot
        would slew it away).
    """

    __slots__ = (
        "actuator",
        "controller",
        "dt_s",
        "gyro",
        "gyro_limit_rad_s",
        "gyro_valid",
        "held_dt_s",
        "last_rates_sent",
        "last_thrust_sent",
        "law_axes",
        "law_ref",
        "out",
        "passthrough",
        "rate_fs_rad_s",
        "rate_max_rad_s",
        "rates_lead_s",
        "shaper",
    )

    def __init__(
        self,
        controller: RateController,
        profile: VehicleProfile,
        *,
        output: str = "actuator",
        rates_full_scale_deg_s: float | None = None,
        rates_lead_s: float = 0.0,
        rates_passthrough: bool = False,
        rates_law_axes: LawAxes | None = None,
        rate_accel_max_rad_s2: tuple[float, float, float] | None = None,
    ) -> None:
        if output not in ("actuator", "rates"):
            raise ValueError(f"output: expected 'actuator' or 'rates', got {output!r}")
        self.controller = controller
        self.actuator = output == "actuator"
        r0, r1, r2 = (math.radians(r) for r in profile.limits.rate_max_deg_s)
        self.rate_max_rad_s = (r0, r1, r2)
        fs = rates_full_scale_deg_s
        self.rate_fs_rad_s = self.rate_max_rad_s if fs is None else (math.radians(fs),) * 3
        self.rates_lead_s = rates_lead_s
        self.passthrough = rates_passthrough
        self.law_axes: LawAxes | None = None
        """The axes the law corrects in rates output (None: all three)."""
        self.set_law_axes(rates_law_axes or ALL_AXES)
        self.gyro_limit_rad_s = (
            math.radians(profile.physics.imu.gyro_range_deg_s) * GYRO_RANGE_MARGIN
        )
        self.gyro: tuple[float, float, float] = NO_RATES
        self.gyro_valid = True
        self.last_thrust_sent = 0.0
        self.dt_s = 0.0
        self.held_dt_s = 0.0
        """The time since the last sample the law flew, over the invalid samples
        since (it holds on them): the next valid sample's step includes it."""
        self.shaper: RateShaper | None = None
        self.law_ref: tuple[float, float, float] = (0.0, 0.0, 0.0)
        """The reference the law was given on the last sample (the pilot's, or
        shaped as the autopilot shapes it)."""
        self.last_rates_sent: tuple[float, float, float] | None = None
        self.out: Any = None
        """The law's output on the last sample (None before the first)."""
        self.set_rate_shaping(rate_accel_max_rad_s2)

    def set_rate_shaping(self, accel_max_rad_s2: tuple[float, float, float] | None) -> None:
        """The autopilot's acceleration limits on body-rate setpoints (None: none),
        as learnt once the stack is known; rates output only. In pass-through the
        law (logged, and judged by the envelope failsafe) flies the shaped
        reference too, and the pilot's rate is sent as it is: the autopilot
        shapes it the same way."""
        self.shaper = (
            RateShaper(accel_max_rad_s2)
            if accel_max_rad_s2 is not None and not self.actuator
            else None
        )

    def set_law_axes(self, axes: LawAxes) -> None:
        """The axes the law corrects in rates output, as chosen once the stack's
        rate gains are known (:mod:`companion.rate_loop`)."""
        self.law_axes = None if all(axes) else axes

    def reset(self) -> None:
        """Forget what the step carries between samples (an engagement starts afresh)."""
        if self.shaper is not None:
            self.shaper.reset()
        self.last_rates_sent = None
        self.held_dt_s = 0.0

    def sample(
        self,
        dt: float,
        gyro: tuple[float, float, float],
        ref: tuple[float, float, float],
        thrust: float,
    ) -> Any:
        """The range gate and the law on one sample; returns the law's output.

        :attr:`gyro` is the sample as the law saw it (NaN when out of range),
        :attr:`gyro_valid` whether it was in range."""
        lim = self.gyro_limit_rad_s
        g0, g1, g2 = gyro
        self.dt_s = dt
        law_dt = dt
        if -lim <= g0 <= lim and -lim <= g1 <= lim and -lim <= g2 <= lim:
            self.gyro_valid = True
            if self.held_dt_s:  # (a step of 0 primes the law: it stays 0)
                law_dt, self.held_dt_s = (dt + self.held_dt_s if dt > 0.0 else 0.0), 0.0
        else:
            self.gyro_valid = False
            gyro = NO_RATES
            self.held_dt_s += dt
        self.gyro = gyro
        shaper = self.shaper
        if shaper is not None:
            ref = shaper.reference(dt, ref)
        self.law_ref = ref
        out = self.out = self.controller.update(law_dt, gyro, ref, thrust)
        return out

    def actuator_command(
        self, out: Any, thrust: float
    ) -> tuple[tuple[float, float, float, float], int]:
        """Actuator controls (roll, pitch, yaw torque, collective) through the last
        gate, and how many fields it replaced."""
        return gate_actuator(out.torque, out.thrust, thrust)

    def rates_command(
        self, out: Any, ref: tuple[float, float, float], thrust: float
    ) -> tuple[tuple[float, float, float], float, int]:
        """Body rates and collective through the last gate, and how many fields it
        replaced.

        The law wraps the autopilot's rate loop: the pilot's rate plus the law's
        correction, within the profile's rate limits (the gate clamps). The
        collective is the pilot's (or the script's): the autopilot mixes it with
        its own rate loop; the law's air-mode shift belongs to torques not sent."""
        shaper = self.shaper
        fs = self.rate_fs_rad_s
        tq = out.torque
        mask = self.law_axes
        if mask is not None and not self.passthrough:
            tq = law_share(tq, mask)
            if shaper is None:
                # Nothing of the law's output went out on the other axes (the
                # shaped path teaches from what was sent, below).
                self.controller.teach_applied(tq)
        if self.passthrough:
            want: tuple[float, float, float] | list[float] = ref
        elif shaper is not None:
            base = self.law_ref
            asked = (base[0] + tq[0] * fs[0], base[1] + tq[1] * fs[1], base[2] + tq[2] * fs[2])
            asked = shaper.within_reach(base, asked)
            want = shaper.limit(self.dt_s, asked, self.last_rates_sent)
        else:
            lead = self.rates_lead_s
            rd = self.controller.reference_rate_dot
            want = [ref[i] + lead * rd[i] + tq[i] * fs[i] for i in range(3)]
        sp, thrust_out, replaced = gate_rates(
            want, thrust, ref, self.rate_max_rad_s, self.last_thrust_sent
        )
        if shaper is not None and not self.passthrough:
            # The law's next lesson: the correction that was sent, not the one asked.
            base = self.law_ref
            self.controller.teach_applied(
                (
                    _unit((sp[0] - base[0]) / fs[0]),
                    _unit((sp[1] - base[1]) / fs[1]),
                    _unit((sp[2] - base[2]) / fs[2]),
                )
            )
        self.last_thrust_sent = thrust_out
        self.last_rates_sent = sp
        return sp, thrust_out, replaced

    def learn(self) -> None:
        """What the law learns from this sample: after the command has left."""
        self.controller.learn()
