"""``companion run``: fly the vehicle's rates with the controller over MAVLink."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click

from companion.cli._failsafe_options import (
    beyond_bounds_opt,
    envelope_error_opt,
    envelope_time_opt,
    hand_back_watch_opt,
    invalid_imu_opt,
    link_timeout_opt,
    on_failsafe_opt,
    on_record_error_opt,
    rc_timeout_opt,
    safe_mode_opt,
    stale_estimate_opt,
    stale_imu_opt,
    stale_position_opt,
)
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
from companion.errors import MfcError
from companion.failsafe import THRESHOLD_MAX, FailsafeConfig
from companion.options import (
    EXIT_BAD_INPUT,
    RUN_DURATION_MAX_S,
    Finite,
    controller_opt,
    live_opt,
    load_inputs,
    mode_opt,
    output_opt,
    profile_opt,
    rates_law_axes_opt,
    signing_key_opt,
    usable_out_dir,
)

if TYPE_CHECKING:
    from companion.fly_check import FlyCheck
    from companion.rate_loop import LawAxes

__all__ = ["run"]

_ARM_TIMEOUT_MAX_S = 600.0
"""``--arm-timeout-s``: ten minutes. ArduCopter's SITL has a position estimate
40-50 s after boot; a real GPS from a cold start takes a few minutes."""


def _fly_check_event(check: FlyCheck, engage: str, skip_fly_check: bool) -> tuple[str, str] | None:
    """The run's event for its controller's fly check, or None for a shipped file;
    exits 2 (nothing opened) for a file that may not fly unchecked."""
    if check.status == "shipped":
        return None
    digest = f"(sha256 {check.sha256[:16]})"
    if check.may_fly:
        return ("fly_check_passed", f"{check.describe()} {digest}")
    if engage == "none":
        return (
            "fly_check_skipped",
            f"{check.describe()} {digest}: flown in shadow mode (--engage none), which "
            "sends nothing",
        )
    if skip_fly_check:
        return (
            "fly_check_skipped",
            f"{check.describe()} {digest}: flown anyway (--skip-fly-check)",
        )
    click.echo(
        f"error: {check.describe()}. A controller file other than the shipped ones flies "
        f"only after it passed the fly check on this computer; {check.advice}, or fly it "
        "unchecked with --skip-fly-check",
        err=True,
    )
    sys.exit(EXIT_BAD_INPUT)


@click.command("run")
@connect_opt
@profile_opt
@controller_opt
@output_opt
@mode_opt(
    "What the sticks ask. rates: body rates (acro). angle: roll and pitch angles up "
    "to 35 deg (self-levelling) and a yaw rate. altitude: as angle, the throttle a climb "
    "rate (altitude held at mid-stick). position: the sticks a velocity, position and "
    "altitude held at mid-stick. The outer loops fly on the autopilot's estimates "
    "(ATTITUDE_QUATERNION, LOCAL_POSITION_NED; stale: failsafe).",
)
@engage_opt
@engage_channel_opt
@click.option(
    "--rates-full-scale-deg-s",
    type=Finite(min=10.0, max=2000.0),
    default=360.0,
    show_default=True,
    help="With --output rates: the rate correction of a full-scale law output.",
)
@click.option(
    "--rates-lead-s",
    type=Finite(min=0.0, max=0.2),
    default=0.03,
    show_default=True,
    help="With --output rates: feed-forward lead on the pilot's rate, s (the autopilot's "
    "rate loop lags its setpoint); 0 turns it off.",
)
@click.option(
    "--rates-passthrough",
    is_flag=True,
    help="With --output rates: send the pilot's rates unchanged (baseline for comparison).",
)
@rates_law_axes_opt
@click.option(
    "--imu-source",
    type=click.Choice(["auto", "highres_imu", "attitude"]),
    default="auto",
    show_default=True,
    help="auto: the stack's (PX4 HIGHRES_IMU, ArduPilot ATTITUDE).",
)
@rate_hz_opt
@click.option(
    "--log-dir",
    type=click.Path(file_okay=False),
    callback=usable_out_dir,
    default=None,
    help="Write flight.tlog, control.mcap and events.jsonl here. An earlier run's are moved "
    "into earlier-<UTC time>/ in it first; a folder another run is using is refused (exit 1).",
)
@click.option("--mqtt", "mqtt_url", default=None, help="mqtt://HOST[:PORT]/PREFIX telemetry.")
@live_opt
@signing_key_opt("MAVLink 2 signing key file (see docs/signing.md).")
@click.option(
    "--duration",
    type=Finite(min=0.0, min_open=True, max=RUN_DURATION_MAX_S),
    default=None,
    help="Stop after this long engaged (sample time, s), handing back; in shadow mode "
    "(--engage none), after this long since the first sample. At most a week.",
)
@on_failsafe_opt
@safe_mode_opt
@hand_back_watch_opt
@stale_imu_opt
@link_timeout_opt
@on_record_error_opt
@invalid_imu_opt
@rc_timeout_opt
@click.option(
    "--mission",
    "mission_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="With --mode position: fly these waypoints (YAML: north_m, east_m, up_m from where "
    "the vehicle engages, speed_m_s, hold_s; docs/flying.md) instead of the sticks; the "
    "engage switch starts and aborts it.",
)
@stale_estimate_opt
@stale_position_opt
@envelope_time_opt
@autopilot_sysid_opt
@click.option(
    "--autopilot-compid",
    type=click.IntRange(1, 255),
    default=None,
    help="With --autopilot-sysid: and only to this component.",
)
@click.option(
    "--reference",
    "reference_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Fly scripted rates from this CSV (companion/reference.py) instead of the sticks.",
)
@click.option(
    "--heartbeat-timeout-s",
    type=Finite(min=0.0, min_open=True, max=3600.0),
    default=10.0,
    show_default=True,
    help="How long to wait for the autopilot's first heartbeat (exit 1 after; at most "
    "an hour, for an autopilot powered long after the companion).",
)
@click.option(
    "--arm-timeout-s",
    type=Finite(min=0.0, max=_ARM_TIMEOUT_MAX_S),
    default=60.0,
    show_default=True,
    help="With --engage auto: keep trying the engage mode and arming this long while the "
    "autopilot refuses them or its pre-arm checks fail (SYS_STATUS), every ~1 s, each "
    "refusal an event with the autopilot's reason; then exit 1 naming the last one. "
    "0: one try each.",
)
@envelope_error_opt
@skip_fly_check_opt
@beyond_bounds_opt
def run(
    connect: str,
    profile_path: Path,
    controller_path: Path | None,
    output: str,
    flight_mode: str,
    engage: str,
    engage_channel: int,
    rates_full_scale_deg_s: float,
    rates_lead_s: float,
    rates_passthrough: bool,
    rates_law_axes: LawAxes | None,
    imu_source: str,
    rate_hz: float,
    log_dir: Path | None,
    mqtt_url: str | None,
    live: tuple[str, int] | None,
    signing_key: Path | None,
    duration: float | None,
    on_failsafe: str,
    safe_mode: str,
    hand_back_watch_s: float,
    stale_imu_s: float,
    link_timeout_s: float,
    on_record_error: str,
    invalid_imu_s: float,
    rc_timeout_s: float,
    mission_path: Path | None,
    stale_estimate_s: float,
    stale_position_s: float,
    envelope_time_s: float,
    autopilot_sysid: int | None,
    autopilot_compid: int | None,
    reference_path: Path | None,
    heartbeat_timeout_s: float,
    arm_timeout_s: float,
    envelope_error_deg_s: float,
    skip_fly_check: bool,
    beyond_bounds: tuple[str, ...],
) -> None:
    """Fly the vehicle's rates with the controller over MAVLink.

    A controller file other than the shipped ones flies only after it passed
    ``companion check-config --controller FILE --fly`` on this computer (or with
    --skip-fly-check, or in shadow mode: either is recorded as an event).
    """
    import asyncio

    from companion.app import Companion, RunOptions
    from companion.flight_modes import FLIGHT_MODES
    from companion.link.signing import load_signing_key
    from companion.link.transport import open_transport

    profile, cfg, ctrl_path = load_inputs(profile_path, controller_path, output)
    warn_profile(profile, profile_path)
    # Check everything a run needs before anything is opened or sent.
    reference = None
    mission = None
    try:
        mode = FLIGHT_MODES[flight_mode]
        if mission_path is not None:
            if not mode.flies_missions:
                fly = " or ".join(m.name for m in FLIGHT_MODES.values() if m.flies_missions)
                raise ValueError(f"--mission: needs --mode {fly} (got --mode {flight_mode})")
            from companion.mission import load_mission

            mission = load_mission(mission_path)
        if rates_passthrough and output != "rates":
            raise ValueError(f"--rates-passthrough: needs --output rates (got --output {output})")
        if rates_law_axes is not None and not all(rates_law_axes) and output != "rates":
            raise ValueError(f"--rates-law-axes: needs --output rates (got --output {output})")
        if reference_path is not None:
            if mode.needs_attitude:
                raise ValueError(
                    "--reference: scripts body rates, needs --mode rates "
                    f"(got --mode {flight_mode})"
                )
            from companion.reference import load_reference

            reference = load_reference(reference_path)
        open_transport(connect)
        if mqtt_url:
            try:
                from companion.telemetry import MqttTelemetry
            except ImportError as exc:
                raise ValueError(
                    f"--mqtt needs aiomqtt ({exc}): pip install 'mfc-companion[mqtt]'"
                ) from exc
            MqttTelemetry(mqtt_url)
        if signing_key:
            load_signing_key(signing_key)
        if on_failsafe == "wait" and engage != "rc-switch":
            raise ValueError(
                f"--on-failsafe wait: needs --engage rc-switch (with {engage} nothing "
                "would engage again; a failsafe ends the run)"
            )
        if autopilot_compid is not None and autopilot_sysid is None:
            raise ValueError("--autopilot-compid: needs --autopilot-sysid as well")
        thresholds = {
            "--stale-imu-s": stale_imu_s,
            "--invalid-imu-s": invalid_imu_s,
            "--link-timeout-s": link_timeout_s,
            "--rc-timeout-s": rc_timeout_s,
            "--stale-estimate-s": stale_estimate_s,
            "--stale-position-s": stale_position_s,
            "--envelope-time-s": envelope_time_s,
            "--envelope-error-deg-s": envelope_error_deg_s,
            "--hand-back-watch-s": hand_back_watch_s,
        }
        for name, value in thresholds.items():
            bound, why = THRESHOLD_MAX[name]
            if value > bound and name not in beyond_bounds:
                raise ValueError(
                    f"{name} {value:g}: beyond {bound:g} ({why}), where the failsafe no "
                    f"longer protects; to fly so anyway, add --beyond-bounds {name}"
                )
    except (ValueError, MfcError) as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(EXIT_BAD_INPUT)
    fly_check_event = _fly_check_event(read_fly_check(ctrl_path), engage, skip_fly_check)
    opts = RunOptions(
        connect=connect,
        profile=profile,
        controller=cfg,
        # Absolute in the log's header, so `companion replay` finds them from anywhere.
        profile_path=str(Path(profile_path).resolve()),
        controller_path=str(Path(ctrl_path).resolve()),
        output=output,  # type: ignore[arg-type]
        mode=flight_mode,  # type: ignore[arg-type]
        mission=mission,
        engage=engage,  # type: ignore[arg-type]
        imu_source=imu_source,  # type: ignore[arg-type]
        loop_rate_hz=rate_hz,
        engage_channel=engage_channel,
        rates_passthrough=rates_passthrough,
        rates_law_axes=rates_law_axes,
        rates_full_scale_deg_s=rates_full_scale_deg_s,
        rates_lead_s=rates_lead_s,
        log_dir=log_dir,
        mqtt_url=mqtt_url,
        live=live,
        signing_key=signing_key,
        duration_s=duration,
        heartbeat_timeout_s=heartbeat_timeout_s,
        arm_timeout_s=arm_timeout_s,
        fly_check_event=fly_check_event,
        reference=reference,
        autopilot_sysid=autopilot_sysid,
        autopilot_compid=autopilot_compid,
        failsafe=FailsafeConfig(
            stale_imu_s=stale_imu_s,
            link_timeout_s=link_timeout_s,
            on_record_error=on_record_error,  # type: ignore[arg-type]
            invalid_imu_s=invalid_imu_s,
            rc_timeout_s=rc_timeout_s,
            stale_estimate_s=stale_estimate_s,
            stale_position_s=stale_position_s,
            envelope_time_s=envelope_time_s,
            tracking_error_max_deg_s=envelope_error_deg_s,
            on_failsafe=on_failsafe,  # type: ignore[arg-type]
            safe_mode=safe_mode,
            hand_back_watch_s=hand_back_watch_s,
            bounds_lifted=tuple(
                f"{name} {thresholds[name]:g} (bound {THRESHOLD_MAX[name][0]:g})"
                for name in sorted(beyond_bounds)
                if thresholds[name] > THRESHOLD_MAX[name][0]
            ),
        ),
    )
    sys.exit(asyncio.run(Companion(opts).run()))
