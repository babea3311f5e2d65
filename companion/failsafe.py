"""The failsafes' thresholds, and the ones judged on each sample.

:class:`FailsafeConfig` is every threshold and what follows a failsafe (the
command line's defaults come from it). :class:`SampleWatch` judges, in sample
time, what one IMU sample can prove: a gyro that stays invalid, a tracking error
or a body rate that stays beyond its limit, a loop that diverges. It only says
so (a :data:`Verdict`); stopping the commands and handing back is the app's.
The wall-clock watchdogs (stale IMU, lost link, lost RC) are the app's too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

__all__ = ["THRESHOLD_MAX", "FailsafeConfig", "SampleWatch", "Verdict"]

Verdict = tuple[str, str]
"""A failsafe's kind (an event name) and its detail."""


def _average_abs(ema: list[float], a: float, e0: float, e1: float, e2: float) -> None:
    """One first-order step (weight ``a``) of the per-axis averages of ``|e|``; a
    NaN (a held output) leaves its axis's average as it was."""
    if e0 == e0:
        ema[0] += a * (abs(e0) - ema[0])
    if e1 == e1:
        ema[1] += a * (abs(e1) - ema[1])
    if e2 == e2:
        ema[2] += a * (abs(e2) - ema[2])


THRESHOLD_MAX: dict[str, tuple[float, str]] = {
    "--stale-imu-s": (1.0, "a vehicle in free fall drops 5 m in 1 s"),
    "--invalid-imu-s": (0.5, "half a second flown on a gyro known to be wrong"),
    "--link-timeout-s": (10.0, "ten lost 1 Hz heartbeats"),
    "--rc-timeout-s": (5.0, "PX4 acts on RC loss after 0.5 s, ArduPilot after 1 s"),
    "--stale-estimate-s": (0.5, "half a second levelled on an attitude nobody measured"),
    "--stale-position-s": (1.0, "a second held on a position nobody measured"),
    "--envelope-time-s": (2.0, "at 720 deg/s, four turns before the envelope acts"),
    "--envelope-error-deg-s": (2000.0, "the usual gyro range: nothing beyond it is measured"),
    "--hand-back-watch-s": (30.0, "a safe mode not shown in 30 s is not coming"),
}
"""The largest value each failsafe threshold of ``companion run`` takes without
``--beyond-bounds``, and why: beyond it the failsafe no longer protects."""


@dataclass(frozen=True)
class FailsafeConfig:
    """Thresholds of the failsafes and what follows one."""

    bounds_lifted: tuple[str, ...] = ()
    """The thresholds (``--`` option names) set beyond :data:`THRESHOLD_MAX` on
    purpose (``--beyond-bounds``): the run records them as an event."""

    stale_imu_s: float = 0.25
    """Failsafe when engaged and no IMU sample processed for this long (wall clock).
    Against the real PX4 v1.16 SITL at 250 Hz the companion saw gaps of at most
    10 ms on an idle 2-core computer, and up to 152 ms (7 over 50 ms in 40 s) with
    both cores kept busy by other programs: 0.1 s failed a loaded companion safe
    in flight with nothing wrong. 0.25 s stays inside the offboard-loss timeout
    preflight recommends (COM_OF_LOSS_T 0.3 s), so the companion's hand-back still
    comes before the autopilot's own."""
    invalid_imu_s: float = 0.05
    invalid_fraction_max: float = 0.2
    """Invalid-IMU failsafe also when this share of the samples, averaged over
    ``invalid_window_s`` (first order, in sample time), is invalid: a gyro that
    fails every other sample never makes a run of ``invalid_imu_s``."""
    invalid_window_s: float = 1.0
    link_timeout_s: float = 3.5
    """Three heartbeat periods at 1 Hz plus jitter: two lost heartbeats in a row
    are not a lost link."""
    rc_timeout_s: float = 0.5
    stale_estimate_s: float = 0.1
    """``--mode angle|altitude|position``: failsafe when engaged and no valid attitude
    estimate came for this long of IMU time (asked for at the IMU's rate)."""
    stale_position_s: float = 0.3
    """``--mode altitude|position``: failsafe when engaged and no valid position
    estimate came for this long of IMU time (asked for at 50 Hz: 15 periods)."""
    tracking_error_max_deg_s: float = 300.0
    envelope_time_s: float = 0.5
    diverging_fraction_max: float = 0.8
    """Diverging-vehicle failsafe (actuator output): the share of samples with one
    motor at full and another at idle together, averaged over
    ``diverging_window_s`` (first order), beyond this while the worst axis's
    tracking error, averaged the same way, is beyond ``diverging_error_min_deg_s``.
    Measured through a delayed link (docs/failsafes.md): normal flights reach
    0.31 (a 2 s mean), a loop oscillating towards the ground 0.97-1.0."""
    diverging_window_s: float = 2.0
    diverging_error_min_deg_s: float = 30.0
    sample_errors_max: int = 3
    """A per-sample step (law, send) that raises this many times in a row is a
    failsafe: at 250 Hz, 12 ms, well inside ``stale_imu_s``."""
    on_record_error: Literal["continue", "failsafe"] = "continue"
    """A record file that cannot be written (disk full): an event and a counter,
    and with "failsafe" a failsafe too."""
    on_failsafe: Literal["exit", "wait"] = "exit"
    safe_mode: str = "auto"
    """The mode to hand back to (companion.stacks), or "auto": a manual mode
    while valid RC is seen (not after RC loss), else hold with a position
    estimate, else land (companion.handback). A named mode whose needs are not
    met is passed over for the pilot-free modes after it."""
    hand_back_watch_s: float = 3.0
    """After a hand-back, how long the autopilot's mode is watched: if it leaves
    the safe mode (its own failsafe) or never shows it, the next one is tried.
    PX4 acts on RC loss after COM_RC_LOSS_T (0.5 s), ArduPilot after
    RC_FS_TIMEOUT (1 s); heartbeats come at 1 Hz."""


class SampleWatch:
    """The failsafes judged on each sample, in sample time (deterministic in
    lockstep; a failed sensor is caught on the sample that proves it).

    Parameters
    ----------
    cfg
        The thresholds.
    rate_max_rad_s
        The profile's body-rate limits.
    motor_idle
        The profile's idle motor command (the low end a diverging loop pins).
    actuator
        Actuator output: the motors are ours, so a diverging loop is judged.
    """

    def __init__(
        self,
        cfg: FailsafeConfig,
        rate_max_rad_s: tuple[float, float, float],
        motor_idle: float,
        *,
        actuator: bool,
    ) -> None:
        self.cfg = cfg
        self.rate_max_rad_s = rate_max_rad_s
        self.actuator = actuator
        self._inv_envelope_time = 1.0 / cfg.envelope_time_s
        self._inv_invalid_window = 1.0 / cfg.invalid_window_s
        self._inv_diverging_window = 1.0 / cfg.diverging_window_s
        self._diverging_err_min_rad_s = math.radians(cfg.diverging_error_min_deg_s)
        self._motor_idle_edge = motor_idle + 0.001
        self._err_max_rad_s = math.radians(cfg.tracking_error_max_deg_s)
        self.invalid_since: float | None = None
        self.invalid_fraction = 0.0
        self.reset()

    # ---------------------------------------------------------------- the gyro
    def reset_invalid(self) -> None:
        """Forget the invalid samples (a new IMU clock)."""
        self.invalid_since = None
        self.invalid_fraction = 0.0

    def valid_sample(self, dt: float) -> None:
        """A sample in range: the run of invalid ones ends, their share decays."""
        self.invalid_since = None
        frac = self.invalid_fraction
        if frac:  # decays while the samples are good; free once it is back to 0
            frac -= frac * dt * self._inv_invalid_window
            self.invalid_fraction = frac if frac > 1e-4 else 0.0

    def invalid_sample(self, t_s: float, dt: float, *, engaged: bool) -> Verdict | None:
        """A sample beyond the sensor's range or not finite (the law held its
        output): a failsafe if this persists, in an unbroken run or as a share
        of the samples."""
        cfg = self.cfg
        a = dt * self._inv_invalid_window
        frac = self.invalid_fraction
        frac += (1.0 - frac) * (a if a < 1.0 else 1.0)
        self.invalid_fraction = frac
        if self.invalid_since is None:
            self.invalid_since = t_s
        if not engaged:
            return None
        if t_s - self.invalid_since > cfg.invalid_imu_s:
            return (
                "failsafe_invalid_imu",
                f"non-finite or out-of-range gyro for {cfg.invalid_imu_s} s of samples",
            )
        if frac > cfg.invalid_fraction_max:
            return (
                "failsafe_invalid_imu",
                f"non-finite or out-of-range gyro in {frac:.0%} of the samples "
                f"(limit {cfg.invalid_fraction_max:.0%} over {cfg.invalid_window_s} s)",
            )
        return None

    # ------------------------------------------------------------ the envelope
    def reset(self) -> None:
        """Start the envelope's averages over (an engagement)."""
        self._err_ema = [0.0, 0.0, 0.0]
        self._err_ema_long = [0.0, 0.0, 0.0]
        self._pinned_ema = 0.0
        self._envelope_since: float | None = None

    def envelope(self, t_s: float, dt: float, gyro: Sequence[float], out: Any) -> Verdict | None:
        """Rates beyond the profile's limits, or a tracking error that stays large.

        The tracking error is averaged (first-order, time constant
        ``envelope_time_s``) so that an acro flip's short error peaks pass
        and a vehicle that has stopped following (a failed motor) does not.
        """
        cfg = self.cfg
        a = dt * self._inv_envelope_time if dt > 0.0 else 0.0
        a = 1.0 if a > 1.0 else a
        ema = self._err_ema
        e0, e1, e2 = out.error
        _average_abs(ema, a, e0, e1, e2)
        worst = max(ema)
        if worst > self._err_max_rad_s:
            return (
                "failsafe_envelope",
                f"tracking error averaged over {cfg.envelope_time_s} s reached "
                f"{math.degrees(worst):.0f} deg/s (limit {cfg.tracking_error_max_deg_s:.0f})",
            )
        if self.actuator:
            verdict = self._diverging(dt, e0, e1, e2, out.motors)
            if verdict is not None:
                return verdict
        r0, r1, r2 = self.rate_max_rad_s
        g0, g1, g2 = gyro
        if not (abs(g0) > r0 or abs(g1) > r1 or abs(g2) > r2):
            self._envelope_since = None
        elif self._envelope_since is None:
            self._envelope_since = t_s
        elif t_s - self._envelope_since >= cfg.envelope_time_s:
            return (
                "failsafe_envelope",
                f"a body rate beyond the profile's limit for {cfg.envelope_time_s} s",
            )
        return None

    @property
    def pinned_fraction(self) -> float:
        """The averaged share of samples with motors at full and at idle together."""
        return self._pinned_ema

    def _diverging(
        self, dt: float, e0: float, e1: float, e2: float, motors: Sequence[float]
    ) -> Verdict | None:
        """A loop that oscillates towards the ground (e.g. through a link it cannot
        fly): motors at full and at idle together for most of a window, with a
        tracking error that does not go away.

        Neither saturation alone (an acro flip saturates for a second) nor the
        error alone (an oscillating loop keeps it under the envelope's limit)
        tells this apart; the two motor ends together, most of the time, do.
        With body-rate output the motors are the autopilot's, not ours: not judged.
        """
        b = dt * self._inv_diverging_window
        b = 1.0 if b > 1.0 else b
        pinned = 1.0 if max(motors) >= 0.999 and min(motors) <= self._motor_idle_edge else 0.0
        pe = self._pinned_ema + b * (pinned - self._pinned_ema)
        self._pinned_ema = pe
        el = self._err_ema_long
        _average_abs(el, b, e0, e1, e2)
        cfg = self.cfg
        if pe > cfg.diverging_fraction_max and max(el) > self._diverging_err_min_rad_s:
            return (
                "failsafe_diverging",
                f"motors at full and idle together in {pe:.0%} of the samples over "
                f"{cfg.diverging_window_s} s with a tracking error of "
                f"{math.degrees(max(el)):.0f} deg/s (limits {cfg.diverging_fraction_max:.0%}, "
                f"{cfg.diverging_error_min_deg_s:.0f} deg/s)",
            )
        return None
