"""What several ``companion`` commands share: the options ``run`` and ``preflight``
both take, the profile's warnings and the controller file's fly check."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from companion.errors import ConfigError
from companion.options import Finite, fail_config

if TYPE_CHECKING:
    from companion.fly_check import FlyCheck

__all__ = [
    "autopilot_sysid_opt",
    "connect_opt",
    "engage_channel_opt",
    "engage_opt",
    "rate_hz_opt",
    "read_fly_check",
    "skip_fly_check_opt",
    "warn_profile",
]


def warn_profile(profile: Any, path: Path) -> None:
    """What in the profile is possible but unlike a multirotor, on stderr."""
    from companion.profile import profile_warnings

    for warning in profile_warnings(profile):
        click.echo(f"warning: {path}: {warning}", err=True)


# Options `companion run` and `companion preflight` share: preflight checks the
# autopilot for the run those options describe.
connect_opt = click.option(
    "--connect",
    default="udpin:0.0.0.0:14540",
    show_default=True,
    help="udpin:HOST:PORT, udpout:HOST:PORT or serial:DEVICE:BAUD.",
)
engage_opt = click.option(
    "--engage",
    type=click.Choice(["auto", "rc-switch", "none"]),
    default="rc-switch",
    show_default=True,
    help="auto: OFFBOARD+arm (simulation); rc-switch: while an RC "
    "channel is high; none: shadow mode, sends no setpoint, mode or arm command.",
)
engage_channel_opt = click.option(
    "--engage-channel", type=click.IntRange(5, 18), default=5, show_default=True
)
rate_hz_opt = click.option(
    "--rate-hz",
    type=Finite(50.0, 1000.0),
    default=250.0,
    show_default=True,
    help="IMU stream (= control loop) rate requested from the autopilot.",
)
autopilot_sysid_opt = click.option(
    "--autopilot-sysid",
    type=click.IntRange(1, 255),
    default=None,
    help="Listen only to this system [default: learnt from the first autopilot heartbeat].",
)
skip_fly_check_opt = click.option(
    "--skip-fly-check",
    is_flag=True,
    help="Fly a controller file that has not passed `companion check-config --controller "
    "FILE --fly` on this computer (its content, by hash) anyway; the run records that the "
    "check was skipped (event fly_check_skipped). Without it such a file is refused (exit "
    "2), unless --engage none. Shipped files need no check.",
)


def read_fly_check(ctrl_path: Path) -> FlyCheck:
    """What this computer knows of the controller file's fly check
    (:func:`companion.fly_check.fly_check_of`); an unreadable file exits 2."""
    from companion.fly_check import fly_check_of

    try:
        return fly_check_of(ctrl_path)
    except ConfigError as exc:
        fail_config(exc)
