"""The ``companion`` command line.

The product's commands (``run``, ``check-config``, ``replay``) live here. The
lab's (``fly``, ``simulate``, ``campaign``, ``envelope``) and the flights of
``check-config --fly`` are the lab's own: found through the entry points it
registers (:mod:`companion.lab`) and loaded only when one of them is asked for, so
a companion computer's install needs neither the simulator nor its plotting.

Exit codes: 0 success, 1 a run that failed (e.g. crashed when asked to fail
on it), 2 bad input (a configuration error names the file and the field;
nothing is started).
"""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from companion import __version__
from companion.errors import EXIT_ERROR, ConfigError, LabMissingError, MfcError
from companion.failsafe import THRESHOLD_MAX, FailsafeConfig
from companion.lab import LAB_COMMANDS, LAB_EXTRA, fly_check_flights, lab_command
from companion.options import (
    EXIT_BAD_INPUT,
    RUN_DURATION_MAX_S,
    WORKERS,
    Finite,
    controller_opt,
    fail_config,
    keep_earlier,
    live_opt,
    load_inputs,
    mode_opt,
    output_opt,
    profile_opt,
    signing_key_opt,
    usable_out_dir,
    usable_out_file,
)

if TYPE_CHECKING:
    from companion.fly_check import FlyCheck

__all__ = ["main"]

_log = logging.getLogger("companion")

_FAILSAFE = FailsafeConfig()
"""The failsafes' defaults: the options below show and use these."""


_THRESHOLD_HARD_MAX_S = 3600.0
"""The most any failsafe's time may be, even with ``--beyond-bounds``: an hour is
past any use (:data:`THRESHOLD_MAX` holds the bounds within which they protect)."""

_ARM_TIMEOUT_MAX_S = 600.0
"""``--arm-timeout-s``: ten minutes. ArduCopter's SITL has a position estimate
40-50 s after boot; a real GPS from a cold start takes a few minutes."""

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


class _Commands(click.Group):
    """The product's commands, and the lab's loaded when one is asked for."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted({*super().list_commands(ctx), *LAB_COMMANDS})

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        cmd = super().get_command(ctx, cmd_name)
        if cmd is not None or cmd_name not in LAB_COMMANDS:
            return cmd
        try:
            return lab_command(cmd_name)
        except LabMissingError as exc:
            return _missing_lab(cmd_name, exc)


def _missing_lab(name: str, exc: LabMissingError) -> click.Command:
    """A stand-in for a lab command this install cannot load: it says why."""

    def fail() -> None:
        raise click.ClickException(
            f"'companion {name}' is a lab command and this install has no lab ({exc}); "
            f"install the project with its simulator: {LAB_EXTRA}"
        )

    return click.Command(
        name,
        callback=fail,
        help="(lab command: not installed here)",
        context_settings={"ignore_unknown_options": True, "allow_extra_args": True},
    )


@click.group(cls=_Commands, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="companion")
@click.option("-v", "--verbose", count=True, help="More logging (-vv for debug).")
def cli(verbose: int) -> None:
    """Model-free control of multirotors from a companion computer."""
    level = logging.WARNING - 10 * min(verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def _warn_profile(profile: Any, path: Path) -> None:
    """What in the profile is possible but unlike a multirotor, on stderr."""
    from companion.profile import profile_warnings

    for warning in profile_warnings(profile):
        click.echo(f"warning: {path}: {warning}", err=True)


# Options `companion run` and `companion preflight` share: preflight checks the
# autopilot for the run those options describe.
_connect_opt = click.option(
    "--connect",
    default="udpin:0.0.0.0:14540",
    show_default=True,
    help="udpin:HOST:PORT, udpout:HOST:PORT or serial:DEVICE:BAUD.",
)
_engage_opt = click.option(
    "--engage",
    type=click.Choice(["auto", "rc-switch", "none"]),
    default="rc-switch",
    show_default=True,
    help="auto: OFFBOARD+arm (simulation); rc-switch: while an RC "
    "channel is high; none: shadow mode, sends no setpoint, mode or arm command.",
)
_engage_channel_opt = click.option(
    "--engage-channel", type=click.IntRange(5, 18), default=5, show_default=True
)
_rate_hz_opt = click.option(
    "--rate-hz",
    type=Finite(50.0, 1000.0),
    default=250.0,
    show_default=True,
    help="IMU stream (= control loop) rate requested from the autopilot.",
)
_autopilot_sysid_opt = click.option(
    "--autopilot-sysid",
    type=click.IntRange(1, 255),
    default=None,
    help="Listen only to this system [default: learnt from the first autopilot heartbeat].",
)
_skip_fly_check_opt = click.option(
    "--skip-fly-check",
    is_flag=True,
    help="Fly a controller file that has not passed `companion check-config --controller "
    "FILE --fly` on this computer (its content, by hash) anyway; the run records that the "
    "check was skipped (event fly_check_skipped). Without it such a file is refused (exit "
    "2), unless --engage none. Shipped files need no check.",
)


def _fly_check(ctrl_path: Path) -> FlyCheck:
    """What this computer knows of the controller file's fly check
    (:func:`companion.fly_check.fly_check_of`); an unreadable file exits 2."""
    from companion.fly_check import fly_check_of

    try:
        return fly_check_of(ctrl_path)
    except ConfigError as exc:
        fail_config(exc)


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


def _remember_fly_check(check: FlyCheck, problems: list[str]) -> None:
    """Record ``check-config --fly``'s verdict for ``companion run`` (stderr says where)."""
    from companion.fly_check import record_fly_check

    verdict = "failed" if problems else "passed"
    try:
        path, note = record_fly_check(check, passed=not problems, problems=problems)
    except (OSError, RuntimeError) as exc:  # RuntimeError: no home folder
        click.echo(
            f"warning: {check.path}: {verdict}, but the verdict cannot be recorded ({exc}): "
            "companion run will not know it",
            err=True,
        )
        return
    if note:
        click.echo(f"warning: {note}: replaced", err=True)
    then = "companion run flies it" if not problems else "companion run refuses it"
    click.echo(
        f"{check.path}: {verdict} the fly check (sha256 {check.sha256[:16]}), recorded in "
        f"{path}: {then}",
        err=True,
    )


@cli.command("check-config")
@profile_opt
@controller_opt
@click.option(
    "--fly",
    is_flag=True,
    help="Also fly the controller config in the bundled simulator (in process, about "
    "10 s of acro on the paper's three vehicles and two envelope corners, the shipped "
    "controller beside it) and fail it (exit 2) when a flight crashes or its error "
    "exceeds the shipped controller's by more than 20 deg/s on an axis.",
)
@click.option(
    "--workers",
    type=WORKERS,
    default=1,
    show_default=True,
    help="Processes for --fly's flights (the result does not depend on it).",
)
def check_config(profile_path: Path, controller_path: Path | None, fly: bool, workers: int) -> None:
    """Validate a profile and a controller config; print the effective values."""
    from companion.config import build_mixer

    profile, cfg, ctrl_path = load_inputs(profile_path, controller_path)
    _warn_profile(profile, profile_path)
    check = _fly_check(ctrl_path)  # its hash before the flights
    mixer = build_mixer(profile)
    roll_f, pitch_f, yaw_f = mixer.factors()
    doc: dict[str, Any] = {
        "profile": {"path": str(profile_path), **profile.model_dump(mode="json")},
        "controller": {"path": str(ctrl_path), **cfg.model_dump(mode="json")},
        "mixer": {"roll": roll_f, "pitch": pitch_f, "yaw": yaw_f, "idle": mixer.idle},
    }
    failed: list[str] = []
    if fly:
        try:
            check_controller = fly_check_flights()
        except LabMissingError as exc:
            click.echo(
                f"error: check-config --fly flies the bundled simulator and this install has "
                f"no lab ({exc}); install the project with its simulator: {LAB_EXTRA}",
                err=True,
            )
            sys.exit(EXIT_BAD_INPUT)
        flights = check_controller(cfg, workers=workers)
        doc["flight_check"] = [f.as_dict() for f in flights]
        failed = [p for f in flights for p in f.problems]
    click.echo(json.dumps(doc, indent=2))
    if fly and check.status != "shipped":
        _remember_fly_check(check, failed)
    elif not fly and not check.may_fly:
        click.echo(f"note: {check.describe()}: companion run refuses it; {check.advice}",
                   err=True)  # fmt: skip
    if failed:
        click.echo(f"error: {ctrl_path}: flown in the simulator, it fails:", err=True)
        for problem in failed:
            click.echo(f"  {problem}", err=True)
        sys.exit(EXIT_BAD_INPUT)


@cli.command("preflight")
@_connect_opt
@profile_opt
@controller_opt
@output_opt
@_engage_opt
@_engage_channel_opt
@_rate_hz_opt
@signing_key_opt("MAVLink 2 signing key file (as companion run will use).")
@_autopilot_sysid_opt
@_skip_fly_check_opt
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
    _warn_profile(profile, profile_path)
    fly_check = _fly_check(ctrl_path)
    try:
        transport = open_transport(connect)
        signing = load_signing_key(signing_key) if signing_key else None
    except (ValueError, MfcError) as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(EXIT_BAD_INPUT)
    link = MavlinkLink(transport, signing=signing, target_system=autopilot_sysid)
    plan = Plan(
        output=output,  # type: ignore[arg-type]
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


@cli.command("run")
@_connect_opt
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
@_engage_opt
@_engage_channel_opt
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
@click.option(
    "--imu-source",
    type=click.Choice(["auto", "highres_imu", "attitude"]),
    default="auto",
    show_default=True,
    help="auto: the stack's (PX4 HIGHRES_IMU, ArduPilot ATTITUDE).",
)
@_rate_hz_opt
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
@click.option(
    "--on-failsafe",
    type=click.Choice(["exit", "wait"]),
    default=_FAILSAFE.on_failsafe,
    show_default=True,
    help="After the hand-back: exit (code 3), or wait for the pilot's switch to engage "
    "again (--engage rc-switch only).",
)
@click.option(
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
@click.option(
    "--hand-back-watch-s",
    type=Finite(min=0.0, max=_THRESHOLD_HARD_MAX_S),
    default=_FAILSAFE.hand_back_watch_s,
    show_default=True,
    help="After a hand-back, watch the autopilot's mode this long: if it leaves the safe "
    "mode (its own failsafe) or never shows it, try the next one. 0: not watched.",
)
@_failsafe_opt(
    "--stale-imu-s",
    "stale_imu_s",
    "Failsafe when engaged and no IMU sample processed for this long.",
)
@_failsafe_opt(
    "--link-timeout-s",
    "link_timeout_s",
    "Failsafe when engaged and no autopilot heartbeat for this long (the default "
    "tolerates two lost 1 Hz heartbeats).",
)
@click.option(
    "--on-record-error",
    type=click.Choice(["continue", "failsafe"]),
    default=_FAILSAFE.on_record_error,
    show_default=True,
    help="A record file that cannot be written (disk full): log it and fly on, or also fail safe.",
)
@_failsafe_opt(
    "--invalid-imu-s",
    "invalid_imu_s",
    "Failsafe after this long of non-finite or out-of-range gyro samples.",
)
@_failsafe_opt(
    "--rc-timeout-s",
    "rc_timeout_s",
    "Failsafe when engaged and no valid RC for this long.",
)
@click.option(
    "--mission",
    "mission_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="With --mode position: fly these waypoints (YAML: north_m, east_m, up_m from where "
    "the vehicle engages, speed_m_s, hold_s; docs/flying.md) instead of the sticks; the "
    "engage switch starts and aborts it.",
)
@_failsafe_opt(
    "--stale-estimate-s",
    "stale_estimate_s",
    "With --mode angle, altitude or position: failsafe when engaged and no valid attitude "
    "estimate for this long of IMU time.",
)
@_failsafe_opt(
    "--stale-position-s",
    "stale_position_s",
    "With --mode altitude or position: failsafe when engaged and no valid position "
    "estimate for this long of IMU time.",
)
@_failsafe_opt(
    "--envelope-time-s",
    "envelope_time_s",
    "How long a rate beyond the profile's limit, or the averaging time of the "
    "tracking error, before the envelope failsafe.",
)
@_autopilot_sysid_opt
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
@_failsafe_opt(
    "--envelope-error-deg-s",
    "tracking_error_max_deg_s",
    "Failsafe when the tracking error averaged over 0.5 s exceeds this.",
    max_=_ERROR_HARD_MAX_DEG_S,
)
@_skip_fly_check_opt
@click.option(
    "--beyond-bounds",
    "beyond_bounds",
    multiple=True,
    type=click.Choice(sorted(THRESHOLD_MAX)),
    help="Let this failsafe threshold exceed its bound (repeatable; recorded as an "
    "event). Bounds: "
    + ", ".join(f"{k} {v:g}" for k, (v, _) in sorted(THRESHOLD_MAX.items()))
    + ".",
)
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
    from companion.link.signing import load_signing_key
    from companion.link.transport import open_transport
    from companion.modes import FLIGHT_MODES

    profile, cfg, ctrl_path = load_inputs(profile_path, controller_path, output)
    _warn_profile(profile, profile_path)
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
    fly_check_event = _fly_check_event(_fly_check(ctrl_path), engage, skip_fly_check)
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


REPLAY_TOLERANCE = 1e-6
"""Outputs are of order 1 to 500 (us for u); the recorded controller reproduces
its flight far closer than this (exactly, on the same machine). Enforced only
when replaying as recorded: no --controller or --profile, and a log that names
its controller file."""


@cli.command("replay")
@click.argument("log", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--controller",
    "controller_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Controller to re-run [default: the one named in the log, else the shipped default].",
)
@click.option(
    "--profile",
    "profile_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Profile whose geometry makes the mixer [default: the one named in the log].",
)
@click.option(
    "--out",
    "out_path",
    type=click.Path(dir_okay=False),
    callback=usable_out_file,
    default=None,
    help="Write the replayed outputs here as a control log, MCAP (an earlier file of that name "
    "is moved into earlier-<UTC time>/ beside it first).",
)
def replay_cmd(
    log: Path, controller_path: Path | None, profile_path: Path | None, out_path: Path | None
) -> None:
    """Re-run a controller offline on a recorded control log (control.mcap).

    With the recorded controller the outputs must match the log (a check that
    the flight was what the code says); with another controller they show what
    it would have commanded on the same samples (open loop).
    """
    from companion.config import DEFAULT_CONTROLLER, load_controller
    from companion.profile import load_profile
    from companion.records import ControlLog, read_control_log
    from companion.replay import compare, replay

    try:
        cols, meta = read_control_log(log)
    except ValueError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(EXIT_BAD_INPUT)
    ctrl = controller_path or Path(meta.get("controller_path") or DEFAULT_CONTROLLER)
    prof = profile_path or (Path(meta["profile_path"]) if meta.get("profile_path") else None)
    if prof is None:
        click.echo(f"error: {log}: no profile_path in the log; give --profile", err=True)
        sys.exit(EXIT_BAD_INPUT)
    try:
        cfg = load_controller(ctrl)
        profile = load_profile(prof)
    except ConfigError as exc:
        fail_config(exc)
    out = replay(cols, cfg, profile, meta=meta)
    diffs = compare(cols, out)
    engaged = int((cols["engaged"] > 0.5).sum())
    click.echo(f"replayed {engaged} engaged samples of {log} with {ctrl} on {prof}")
    if meta.get("cut_short") == "true":
        click.echo(
            f"note: {log} was not closed by its writer (killed?): read up to its last whole chunk",
            err=True,
        )
    worst = max(diffs.values()) if diffs else 0.0
    for name, d in sorted(diffs.items(), key=lambda kv: -kv[1])[:8]:
        click.echo(f"  {name:24s} max |recorded - replayed| = {d:.3g}")
    click.echo(f"largest difference: {worst:.3g}")
    if out_path is not None:
        keep_earlier(f"--out {out_path}", out_path.parent, (out_path.name,))
        names = list(out)
        with ControlLog(
            out_path, names, meta={"replay_of": str(log), "controller": str(ctrl)}
        ) as w:
            for row in zip(*(out[n].tolist() for n in names), strict=True):
                w.append(row)
        click.echo(f"wrote {out_path}")
    as_recorded = (
        controller_path is None and profile_path is None and bool(meta.get("controller_path"))
    )
    if as_recorded and worst > REPLAY_TOLERANCE:
        # The recorded controller and profile must reproduce their own flight: the
        # laws are deterministic, so a difference means something changed since.
        click.echo(
            f"error: the recorded controller {ctrl} on {prof} does not reproduce {log} "
            f"(largest difference {worst:.3g} > {REPLAY_TOLERANCE:g}): one of the two files "
            "or the code has changed since the flight, or the log was written on another "
            "kind of machine (its floating-point library may round differently)",
            err=True,
        )
        sys.exit(1)


def main() -> None:
    """Console-script entry point."""
    cli(prog_name="companion")


if __name__ == "__main__":
    main()
