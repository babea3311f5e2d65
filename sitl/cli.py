"""``sitl``: run the bundled PX4-like SITL from the command line.

Usage::

    sitl run --profile vehicle_profiles/f450.yaml --mavlink udpout:127.0.0.1:14540 \\
        --pilot paper-acro --seed 1 --clock realtime --duration 30 --log out/flight.npz
    sitl run --profile vehicle_profiles/f450.yaml --firmware 1.14.0 \\
        --param COM_OF_LOSS_T=0.5 --param RC_MAP_ROLL=2
    sitl envelope --n 30 --seed 1 --out runs/envelope --corners

Neither overwrites an earlier run: its files (``--log FILE`` and its events,
``--out``'s profiles and envelope.json) are first moved into
``earlier-<UTC time>/`` in their folder.

Exit codes: 0 when the flight ran (completed, stopped by SIGINT/SIGTERM, or
crashed: the outcome is in the log summary), 2 for bad arguments or a bad
profile / stick script (the message goes to stderr, nothing is started), 1 for
an unexpected failure (e.g. the UDP port cannot be bound).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any

import click

from companion.errors import ConfigError, SigningError
from companion.options import (
    SEED,
    SIM_DURATION_MAX_S,
    Finite,
    find_profile,
    keep_earlier,
    signing_key_opt,
    usable_out_dir,
    usable_out_file,
)
from companion.profile import load_profile
from sitl.link_model import LINK_PROFILES, LinkSpec, parse_link
from sitl.personality import FirmwareVersion
from sitl.scenario import GUST_SIGMA_MAX_M_S

ENVELOPE_N_MAX = 10_000
"""``--n``: the envelope study samples 30 vehicles; ten thousand is a campaign's worth."""

__all__ = ["cli", "main"]

logger = logging.getLogger("sitl")


def _firmware_opt(
    ctx: click.Context, param: click.Parameter, value: str | None
) -> FirmwareVersion | None:
    """``--firmware``: a version the face reports, checked before anything starts."""
    if value is None:
        return None
    try:
        return FirmwareVersion.parse(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc), ctx=ctx, param=param) from None


def _link_opt(ctx: click.Context, param: click.Parameter, value: str | None) -> LinkSpec | None:
    """``--link``: a profile or fields, checked before anything starts."""
    if value is None:
        return None
    try:
        return parse_link(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc), ctx=ctx, param=param) from None


_MODES = ["MANUAL", "ALTCTL", "POSCTL", "ACRO", "STABILIZED"]
_COPTER_MODES = ["STABILIZE", "ALT_HOLD", "GUIDED", "GUIDED_NOGPS", "LAND"]


@click.group()
@click.option("-v", "--verbose", count=True, help="More logging (-v info, -vv debug).")
def cli(verbose: int) -> None:
    """The bundled PX4-like quadrotor SITL (MAVLink 2)."""
    level = logging.WARNING - 10 * min(verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s %(message)s")


@cli.command()
@click.option(
    "--profile",
    "profile_path",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    callback=find_profile,
    help="Vehicle profile YAML (a relative path not found here is also looked up among "
    "the bundled profiles, so vehicle_profiles/NAME.yaml works from any directory).",
)
@click.option(
    "--mavlink",
    default="udpout:127.0.0.1:14540",
    show_default=True,
    help="udpout:HOST:PORT (send there, answer any sender) or udpin:HOST:PORT (listen).",
)
@click.option("--pilot", default=None, help="Maneuver name or stick-script YAML; none: no RC.")
@click.option(
    "--seed",
    default=None,
    type=SEED,
    help="Seed of all randomness [default: the scenario's, or 0].",
)
@click.option(
    "--clock", type=click.Choice(["realtime", "lockstep"]), default="realtime", show_default=True
)
@click.option(
    "--duration",
    "duration_s",
    type=Finite(min=0.0, min_open=True, max=SIM_DURATION_MAX_S),
    default=None,
    help="Simulated seconds, at most an hour [default: the pilot's duration, else until "
    "SIGINT/SIGTERM].",
)
@click.option("--test-stand", is_flag=True, help="Vehicle on a gimbal rig: attitude only.")
@click.option(
    "--wind-gust",
    "wind_gust_m_s",
    type=Finite(min=0.0, max=GUST_SIGMA_MAX_M_S),
    default=0.0,
    show_default=True,
    help="Turbulence intensity, m/s (per-axis sigma; at most a scenario's bound).",
)
@click.option(
    "--log",
    "log_path",
    type=click.Path(dir_okay=False),
    callback=usable_out_file,
    default=None,
    help="True-state log (.npz) plus FILE.events.jsonl; see sitl.runner. Earlier ones of "
    "those names are moved into earlier-<UTC time>/ beside them first.",
)
@click.option(
    "--offboard-timeout",
    "offboard_timeout_s",
    type=Finite(min=0.0, min_open=True, max=60.0),
    default=1.0,
    show_default=True,
    help="Offboard loss failsafe timeout, s (PX4 COM_OF_LOSS_T, whose range is 0-60 s; "
    "--param COM_OF_LOSS_T wins).",
)
@click.option(
    "--lockstep-timeout",
    "lockstep_timeout_s",
    type=Finite(min=0.0, min_open=True, max=60.0),
    default=0.5,
    show_default=True,
    help="Longest wall-clock wait for a setpoint in lockstep, s (at most a minute: a "
    "companion silent that long has stopped).",
)
@click.option(
    "--mode",
    "initial_mode",
    type=click.Choice(_MODES + _COPTER_MODES, case_sensitive=False),
    default=None,
    help="Mode at boot [default: ACRO with a pilot, else MANUAL (px4) / STABILIZE "
    "(ardupilot)]; PX4 names for px4, Copter names (and ACRO) for ardupilot.",
)
@click.option("--no-auto-arm", is_flag=True, help="Do not arm at t=0 when a pilot is given.")
@click.option(
    "--scenario",
    default=None,
    help="Scenario name or file (sitl/scenarios): pilot, seed, wind, IMU and RC rate from it; "
    "explicit options override it.",
)
@click.option(
    "--pilot-from-arm",
    is_flag=True,
    help="Start the pilot's timeline when the vehicle is armed (for a companion that arms it).",
)
@click.option(
    "--fault",
    "faults",
    multiple=True,
    help="Inject a fault: imu-stop@T, imu-nan@T, imu-range@T, link-drop@T, "
    "heartbeat-stop@T, rc-lost@T, motor-fail@T:INDEX (T in simulated s; repeatable).",
)
@click.option(
    "--autopilot",
    "autopilot",
    type=click.Choice(["px4", "ardupilot"]),
    default="px4",
    show_default=True,
    help="Personality shown over MAVLink: PX4 or ArduCopter (docs/research/ardupilot.md).",
)
@click.option(
    "--prearm-fail",
    "prearm_fail",
    default=None,
    metavar="TEXT",
    help="ardupilot: a pre-arm check fails with TEXT (arming FAILED + 'PreArm: TEXT').",
)
@signing_key_opt(
    "MAVLink 2 signing key file (as companion run --signing-key): sign all, accept only signed."
)
@click.option(
    "--param",
    "ap_params",
    multiple=True,
    metavar="NAME=VALUE",
    help="Set a parameter at boot (repeatable), any of the personality's table, served "
    "over MAVLink: px4 (sitl.px4_params), e.g. COM_OF_LOSS_T=0.5, NAV_RCL_ACT=3, "
    "COM_RCL_EXCEPT=4, COM_RC_IN_MODE=1, RC_MAP_ROLL=2, IMU_GYRO_RATEMAX=250, "
    "MAV_SYS_ID=2; ardupilot (sitl.ardupilot_params), e.g. SCHED_LOOP_RATE=200, "
    "GUID_OPTIONS=8, FS_THR_ENABLE=0, RCMAP_ROLL=2. An unknown name lists the table.",
)
@click.option(
    "--firmware",
    "firmware",
    default=None,
    callback=_firmware_opt,
    metavar="X.Y.Z",
    help="Firmware version AUTOPILOT_VERSION reports, MAJOR.MINOR.PATCH[-dev|-alpha|-beta|-rcN] "
    "[default: px4 1.13.3, ardupilot 4.7.0-dev]. PX4 1.14 and later drop "
    "SET_ACTUATOR_CONTROL_TARGET and clear its capability bit, as real PX4 does.",
)
@click.option(
    "--no-rc",
    is_flag=True,
    help="The vehicle has no radio: the pilot's sticks never reach the autopilot "
    "(RC_CHANNELS without channels), as for a vehicle flown by a script.",
)
@click.option(
    "--pilot-input",
    type=click.Choice(["rc", "joystick"]),
    default="rc",
    show_default=True,
    help="How the pilot's sticks reach the autopilot: rc, a radio (RC_CHANNELS); "
    "joystick (PX4 only), a ground station's MANUAL_CONTROL as PX4 SIH is flown: "
    "no RC_CHANNELS, PX4 streams MANUAL_CONTROL back on request, aux1 is the "
    "pilot's channel 5 (the engage switch).",
)
@click.option(
    "--ekf-warmup",
    "ekf_warmup",
    default=None,
    metavar="ALT_S,POS_S",
    help="ArduPilot: the EKF has an altitude estimate ALT_S and a position estimate "
    "POS_S seconds after boot (the real ArduCopter 4.5.6 SITL: about 3 and 40-50 s); "
    "before, arming is refused ('Arm: Need Alt Estimate', 'PreArm: Need Position "
    "Estimate' in modes that need one) [default: ready at boot].",
)
@click.option(
    "--no-position",
    is_flag=True,
    help="The vehicle has no position estimate (no GPS or flow): no LOCAL_POSITION_NED, "
    "hold modes refused.",
)
@click.option(
    "--true-state",
    is_flag=True,
    help="Stream the true attitude, position and velocity (ATTITUDE, ATTITUDE_QUATERNION, "
    "LOCAL_POSITION_NED) at every step instead of the estimator model's output "
    "(sitl.estimator_model EKF_GPS: an EKF's errors, lag and rate).",
)
@click.option(
    "--link",
    "link",
    default=None,
    callback=_link_opt,
    metavar="SPEC",
    help="The companion link (sitl.link_model): a profile, "
    f"{', '.join(LINK_PROFILES)}, or fields such as delay_ms=5,jitter_ms=2,loss=0.01 "
    "(delay_ms, jitter_ms, up_/down_delay_ms, up_/down_jitter_ms, loss, duplicate, "
    "fifo), or a profile with fields changed (wifi,loss=0) "
    "[default: the scenario's, else ideal].",
)
def run(
    profile_path: Path,
    mavlink: str,
    pilot: str | None,
    seed: int | None,
    clock: str,
    duration_s: float | None,
    test_stand: bool,
    wind_gust_m_s: float,
    log_path: Path | None,
    offboard_timeout_s: float,
    lockstep_timeout_s: float,
    initial_mode: str | None,
    no_auto_arm: bool,
    scenario: str | None,
    pilot_from_arm: bool,
    faults: tuple[str, ...],
    autopilot: str,
    prearm_fail: str | None,
    ap_params: tuple[str, ...],
    no_position: bool,
    no_rc: bool,
    pilot_input: str,
    ekf_warmup: str | None,
    true_state: bool,
    signing_key: Path | None,
    link: LinkSpec | None,
    firmware: FirmwareVersion | None,
) -> None:
    """Run one simulated flight."""
    from sitl.estimator_model import EKF_GPS
    from sitl.mavlink_link import parse_endpoint
    from sitl.runner import RunConfig, Runner

    try:
        endpoint = parse_endpoint(mavlink)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--mavlink") from exc
    if pilot is not None and not pilot.strip():
        raise click.BadParameter(
            "expected a maneuver name or a stick-script file", param_hint="--pilot"
        )
    try:
        profile = load_profile(profile_path, simulated=True)
        extra: dict[str, Any] = {}
        if scenario is not None:
            from sitl.scenario import load_scenario

            sc = load_scenario(scenario, check_pilot=pilot is None)
            link = sc.link if link is None else link
            pilot = pilot or sc.pilot
            seed = sc.seed if seed is None else seed
            duration_s = duration_s if duration_s is not None else sc.duration_s
            test_stand = test_stand or not sc.free_flight
            extra = {
                "wind": sc.wind.config() if wind_gust_m_s == 0.0 else None,
                "imu_model": sc.imu_model(profile),
                "rc_period_s": 1.0 / sc.rc_rate_hz,
                "dt_s": sc.physics_dt_s,
            }
        from sitl.faults import parse_fault

        parsed_faults = tuple(parse_fault(f) for f in faults)
        parsed_params = tuple(_parse_param(p) for p in ap_params)
        _check_param_names(autopilot, firmware, parsed_params)
        if autopilot != "ardupilot" and prearm_fail is not None:
            raise ValueError("--prearm-fail needs --autopilot ardupilot")
        warmup = None
        if ekf_warmup is not None:
            if autopilot != "ardupilot":
                raise ValueError("--ekf-warmup needs --autopilot ardupilot")
            try:
                alt_s, pos_s = (float(v) for v in ekf_warmup.split(","))
            except ValueError:
                raise ValueError(
                    f"--ekf-warmup {ekf_warmup!r}: expected ALT_S,POS_S (e.g. 3,45)"
                ) from None
            warmup = (alt_s, pos_s)
        key = None
        if signing_key is not None:
            from companion.link.signing import load_signing_key

            key = load_signing_key(signing_key).key
        config = RunConfig(
            mavlink=endpoint,
            pilot=pilot,
            seed=0 if seed is None else seed,
            clock=clock,  # type: ignore[arg-type]
            duration_s=duration_s,
            test_stand=test_stand,
            wind_gust_m_s=wind_gust_m_s,
            log_path=log_path,
            offboard_timeout_s=offboard_timeout_s,
            lockstep_timeout_s=lockstep_timeout_s,
            initial_mode=initial_mode,
            auto_arm=not no_auto_arm,
            pilot_from_arm=pilot_from_arm,
            faults=parsed_faults,
            signing_key=key,
            autopilot=autopilot,  # type: ignore[arg-type]
            prearm_fail=prearm_fail,
            ardupilot_params=parsed_params if autopilot == "ardupilot" else (),
            px4_params=parsed_params if autopilot == "px4" else (),
            firmware=firmware,
            position=not no_position,
            rc=not no_rc,
            pilot_input=pilot_input,  # type: ignore[arg-type]
            ekf_warmup_s=warmup,
            link=LINK_PROFILES["ideal"] if link is None else link,
            estimator=None if true_state else EKF_GPS,
            **extra,
        )
        runner = Runner(profile, config, profile_name=str(profile_path))
    except (ConfigError, SigningError, ValueError) as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    if log_path is not None:
        from sitl.flight_log import events_path

        names = (log_path.name, events_path(log_path).name)
        keep_earlier(f"--log {log_path}", log_path.parent, names)
    try:
        summary = runner.run()
    except OSError as exc:
        click.echo(f"error: MAVLink {endpoint}: {exc}", err=True)
        sys.exit(1)
    click.echo(
        f"{summary.status}: {summary.sim_time_s:.2f} s simulated in {summary.wall_time_s:.2f} s"
        f" ({summary.realtime_factor:.2f}x), final mode {summary.final_mode}",
        err=True,
    )
    if summary.link_counts:
        c = summary.link_counts
        click.echo(
            f"link {summary.link}: {c['up_sent']} frames up ({c['up_lost']} lost, "
            f"{c['up_duplicated']} duplicated), {c['down_sent']} down ({c['down_lost']} lost, "
            f"{c['down_duplicated']} duplicated)",
            err=True,
        )


@cli.command()
@click.option(
    "--n",
    "n",
    type=click.IntRange(min=0, max=ENVELOPE_N_MAX),
    default=30,
    show_default=True,
    help="Vehicles sampled from the envelope (Latin hypercube).",
)
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the sample.")
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False),
    callback=usable_out_dir,
    help="Directory for NAME.yaml per vehicle and envelope.json (an earlier run's *.yaml "
    "and envelope.json are moved into earlier-<UTC time>/ in it first).",
)
@click.option("--corners", "with_corners", is_flag=True, help="Also write the named corners.")
def envelope(n: int, seed: int, out_dir: Path, with_corners: bool) -> None:
    """Write envelope profiles (sitl.envelope), one YAML each, and envelope.json."""
    import json

    from sitl.envelope import corners, sample_envelope, write_profile_yaml

    vehicles = (sample_envelope(n, seed) if n > 0 else []) + (corners() if with_corners else [])
    if not vehicles:
        raise click.UsageError("nothing to write: give --n 1 or more, or --corners")
    keep_earlier(f"--out {out_dir}", out_dir, ("*.yaml", "envelope.json"))
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        for v in vehicles:
            write_profile_yaml(v.profile(), out_dir / f"{v.name}.yaml")
        figures = json.dumps([v.to_dict() for v in vehicles], indent=2)
        (out_dir / "envelope.json").write_text(figures + "\n", encoding="utf-8")
    except OSError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(1)
    click.echo(f"{len(vehicles)} profiles and envelope.json written to {out_dir}", err=True)


def _check_param_names(
    autopilot: str, firmware: FirmwareVersion | None, params: tuple[tuple[str, float], ...]
) -> None:
    """``--param``: every name is in the personality's table (for that firmware)."""
    if autopilot == "ardupilot":
        from sitl.ardupilot_params import ArduParams

        names = ArduParams().names
    else:
        from sitl.px4_params import PX4_DEFAULT_FIRMWARE, Px4Params

        names = Px4Params(firmware or PX4_DEFAULT_FIRMWARE).names
    for name, _ in params:
        if name not in names:
            raise click.BadParameter(
                f"{autopilot} has no parameter {name!r} in the SITL: expected one of "
                f"{', '.join(names)}",
                param_hint="--param",
            )


_FLOAT32_MAX = 3.4028234663852886e38
"""The largest float32: MAVLink carries a parameter's value as one (PARAM_VALUE)."""


def _parse_param(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    try:
        if not sep or not name.strip():
            raise ValueError
        number = float(value)
    except ValueError:
        raise ValueError(f"--param {text!r}: expected NAME=NUMBER") from None
    if abs(number) > _FLOAT32_MAX:  # nan and inf pass here: the personality names them
        raise ValueError(f"--param {text!r}: beyond a float32, which MAVLink carries it in")
    return name.strip().upper(), number


def main() -> None:
    """Console-script entry point."""
    cli()
