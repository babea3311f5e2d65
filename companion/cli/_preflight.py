"""``companion preflight``: check the autopilot is set up for ``companion run``."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import click

from companion.cli._shared import (
    autopilot_sysid_opt,
    connect_opt,
    engage_channel_opt,
    engage_opt,
    rate_hz_opt,
    read_fly_check,
    skip_fly_check_opt,
    warn_profile,
)
from companion.errors import EXIT_ERROR, MfcError
from companion.options import (
    EXIT_BAD_INPUT,
    Finite,
    controller_opt,
    load_inputs,
    output_opt,
    profile_opt,
    rates_law_axes_opt,
    signing_key_opt,
)
from companion.rate_loop import LawAxes

__all__ = ["preflight"]


@click.command("preflight")
@connect_opt
@profile_opt
@controller_opt
@output_opt
@rates_law_axes_opt
@engage_opt
@engage_channel_opt
@rate_hz_opt
@signing_key_opt("MAVLink 2 signing key file (as companion run will use).")
@autopilot_sysid_opt
@skip_fly_check_opt
@click.option(
    "--watch-s",
    type=Finite(min=1.0, max=120.0),
    default=3.0,
    show_default=True,
    help="How long to watch the streams (flip the engage switch meanwhile).",
)
@click.option(
    "--heartbeat-timeout-s",
    type=Finite(min=0.1, max=60.0),
    default=5.0,
    show_default=True,
    help="How long to wait for the autopilot's HEARTBEAT.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the checklist as JSON.")
def preflight(
    connect: str,
    profile_path: Path,
    controller_path: Path | None,
    output: str,
    rates_law_axes: LawAxes | None,
    engage: str,
    engage_channel: int,
    rate_hz: float,
    signing_key: Path | None,
    autopilot_sysid: int | None,
    skip_fly_check: bool,
    watch_s: float,
    heartbeat_timeout_s: float,
    as_json: bool,
) -> None:
    """Check the autopilot is set up for companion run; move nothing.

    Reads the stack and its version, the parameters a safe offboard flight
    needs, the IMU rate and the link's round trip, the radio and the engage
    switch, signing, the landed state and the position estimate, says whether the
    controller file passed the fly check here, and times the control law here. Each
    line passes, warns or fails with the fix. Exit 0 when nothing fails, 1
    otherwise, 2 for bad input.
    """
    import asyncio

    from companion.config import build_controller
    from companion.control import COMPILED
    from companion.link.mavlink import MavlinkLink
    from companion.link.signing import load_signing_key
    from companion.link.transport import open_transport
    from companion.preflight import Plan, as_data, judge, measure_core, observe, summary

    profile, cfg, ctrl_path = load_inputs(profile_path, controller_path, output)
    warn_profile(profile, profile_path)
    fly_check = read_fly_check(ctrl_path)
    try:
        transport = open_transport(connect)
        signing = load_signing_key(signing_key) if signing_key else None
    except (ValueError, MfcError) as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(EXIT_BAD_INPUT)
    link = MavlinkLink(transport, signing=signing, target_system=autopilot_sysid)
    plan = Plan(
        output=output,  # type: ignore[arg-type]
        rates_law_axes=rates_law_axes,
        engage=engage,  # type: ignore[arg-type]
        engage_channel=engage_channel,
        rate_hz=rate_hz,
        sticks_channels=cfg.sticks.channels,
        signing=signing is not None,
        serial=connect.startswith("serial:"),
        source_system=link.source_system,
        source_component=link.source_component,
        fly_check=fly_check,
        skip_fly_check=skip_fly_check,
    )

    async def observed() -> Any:
        try:
            return await observe(
                link, plan, watch_s=watch_s, heartbeat_timeout_s=heartbeat_timeout_s
            )
        finally:
            await link.close()

    try:
        obs = asyncio.run(observed())
    except OSError as exc:
        click.echo(f"error: {connect}: {exc}", err=True)
        sys.exit(EXIT_ERROR)
    # Timed after the link is closed, so the watch and the timing do not disturb each other.
    core = measure_core(build_controller(cfg, profile), COMPILED, rate_hz)
    checks = judge(obs, plan, core)
    counts = summary(checks)
    if as_json:
        click.echo(json.dumps(as_data(obs, checks, core), indent=2))
    else:
        width = min(16, max(len(c.name) for c in checks))
        for c in checks:
            click.echo(f"{c.status.upper():4}  {c.name:<{width}}  {c.detail}")
            if c.fix and c.status != "pass":
                click.echo(f"{'':4}  {'':<{width}}  fix: {c.fix}")
        click.echo(f"{counts['fail']} failed, {counts['warn']} warnings, {counts['pass']} passed")
    sys.exit(EXIT_ERROR if counts["fail"] else 0)
