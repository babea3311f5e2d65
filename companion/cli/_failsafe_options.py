"""The failsafe options of ``companion run``: each threshold, what a failsafe does
and which mode it hands back to, with :class:`~companion.failsafe.FailsafeConfig`'s
defaults and the bounds of :data:`~companion.failsafe.THRESHOLD_MAX`."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

from companion.failsafe import THRESHOLD_MAX, FailsafeConfig
from companion.options import Finite

__all__ = [
    "beyond_bounds_opt",
    "envelope_error_opt",
    "envelope_time_opt",
    "hand_back_watch_opt",
    "invalid_imu_opt",
    "link_timeout_opt",
    "on_failsafe_opt",
    "on_record_error_opt",
    "rc_timeout_opt",
    "safe_mode_opt",
    "stale_estimate_opt",
    "stale_imu_opt",
    "stale_position_opt",
]

_FAILSAFE = FailsafeConfig()
"""The failsafes' defaults: the options below show and use these."""


_THRESHOLD_HARD_MAX_S = 3600.0
"""The most any failsafe's time may be, even with ``--beyond-bounds``: an hour is
past any use (:data:`THRESHOLD_MAX` holds the bounds within which they protect)."""

_ERROR_HARD_MAX_DEG_S = 4000.0
"""``--envelope-error-deg-s``, even with ``--beyond-bounds``: the widest gyro range
made (+-4000 deg/s); no error beyond it is measured."""


def _failsafe_opt(
    name: str, field: str, help_: str, max_: float = _THRESHOLD_HARD_MAX_S
) -> Callable[[Callable[..., Any]], Any]:
    """A failsafe's threshold (a positive, finite number up to ``max_``), defaulting
    to FailsafeConfig's."""
    return click.option(
        name,
        type=Finite(min=0.0, min_open=True, max=max_),
        default=getattr(_FAILSAFE, field),
        show_default=True,
        help=help_,
    )


on_failsafe_opt = click.option(
    "--on-failsafe",
    type=click.Choice(["exit", "wait"]),
    default=_FAILSAFE.on_failsafe,
    show_default=True,
    help="After the hand-back: exit (code 3), or wait for the pilot's switch to engage "
    "again (--engage rc-switch only).",
)
safe_mode_opt = click.option(
    "--safe-mode",
    type=click.Choice(
        [
            "auto",
            "posctl",
            "altctl",
            "stabilized",
            "manual",
            "hold",
            "alt_hold",
            "stabilize",
            "loiter",
            "brake",
            "land",
        ]
    ),
    default=_FAILSAFE.safe_mode,
    show_default=True,
    help="Mode handed back to. auto: a manual mode while valid RC is seen (not after RC "
    "loss), else hold with a position estimate, else land (PX4 posctl/altctl, hold, land; "
    "ArduPilot alt_hold, loiter, land). Named: PX4 posctl/altctl/stabilized/manual/hold/"
    "land; ArduPilot alt_hold/stabilize/loiter/brake/land (checked on connect); one whose "
    "needs are not met gives way to the pilot-free modes after it.",
)
hand_back_watch_opt = click.option(
    "--hand-back-watch-s",
    type=Finite(min=0.0, max=_THRESHOLD_HARD_MAX_S),
    default=_FAILSAFE.hand_back_watch_s,
    show_default=True,
    help="After a hand-back, watch the autopilot's mode this long: if it leaves the safe "
    "mode (its own failsafe) or never shows it, try the next one. 0: not watched.",
)
stale_imu_opt = _failsafe_opt(
    "--stale-imu-s",
    "stale_imu_s",
    "Failsafe when engaged and no IMU sample processed for this long.",
)
link_timeout_opt = _failsafe_opt(
    "--link-timeout-s",
    "link_timeout_s",
    "Failsafe when engaged and no autopilot heartbeat for this long (the default "
    "tolerates two lost 1 Hz heartbeats).",
)
on_record_error_opt = click.option(
    "--on-record-error",
    type=click.Choice(["continue", "failsafe"]),
    default=_FAILSAFE.on_record_error,
    show_default=True,
    help="A record file that cannot be written (disk full): log it and fly on, or also fail safe.",
)
invalid_imu_opt = _failsafe_opt(
    "--invalid-imu-s",
    "invalid_imu_s",
    "Failsafe after this long of non-finite or out-of-range gyro samples.",
)
rc_timeout_opt = _failsafe_opt(
    "--rc-timeout-s",
    "rc_timeout_s",
    "Failsafe when engaged and no valid RC for this long.",
)
stale_estimate_opt = _failsafe_opt(
    "--stale-estimate-s",
    "stale_estimate_s",
    "With --mode angle, altitude or position: failsafe when engaged and no valid attitude "
    "estimate for this long of IMU time.",
)
stale_position_opt = _failsafe_opt(
    "--stale-position-s",
    "stale_position_s",
    "With --mode altitude or position: failsafe when engaged and no valid position "
    "estimate for this long of IMU time.",
)
envelope_time_opt = _failsafe_opt(
    "--envelope-time-s",
    "envelope_time_s",
    "How long a rate beyond the profile's limit, or the averaging time of the "
    "tracking error, before the envelope failsafe.",
)
envelope_error_opt = _failsafe_opt(
    "--envelope-error-deg-s",
    "tracking_error_max_deg_s",
    "Failsafe when the tracking error averaged over 0.5 s exceeds this.",
    max_=_ERROR_HARD_MAX_DEG_S,
)
beyond_bounds_opt = click.option(
    "--beyond-bounds",
    "beyond_bounds",
    multiple=True,
    type=click.Choice(sorted(THRESHOLD_MAX)),
    help="Let this failsafe threshold exceed its bound (repeatable; recorded as an "
    "event). Bounds: "
    + ", ".join(f"{k} {v:g}" for k, (v, _) in sorted(THRESHOLD_MAX.items()))
    + ".",
)
