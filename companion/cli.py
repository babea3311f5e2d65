"""The ``companion`` command line.

Exit codes: 0 success, 1 a run that failed (e.g. crashed when asked to fail
on it), 2 bad input (a configuration error names the file and the field;
nothing is started).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import click
from click.core import ParameterSource

from companion import __version__
from companion._options import SEED, Finite, usable_out_dir, usable_out_file
from companion.errors import ConfigError, MfcError

__all__ = ["main"]

_log = logging.getLogger("companion")

EXIT_BAD_INPUT = 2


@contextlib.contextmanager
def _percent_bar(desc: str, enabled: bool) -> Iterator[Callable[[float], None]]:
    """A tqdm bar in percent; yields the ``progress(fraction)`` callback flights take."""
    from tqdm import tqdm

    bar = tqdm(total=100, desc=desc, unit="%", disable=not enabled)
    done = [0]

    def tick(frac: float) -> None:
        n = int(frac * 100)
        if n > done[0]:
            bar.update(n - done[0])
            done[0] = n

    try:
        yield tick
    finally:
        bar.close()


def _fail_config(exc: ConfigError) -> None:
    click.echo(f"error: {exc}", err=True)
    sys.exit(EXIT_BAD_INPUT)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="companion")
@click.option("-v", "--verbose", count=True, help="More logging (-vv for debug).")
def cli(verbose: int) -> None:
    """Model-free control of multirotors from a companion computer."""
    level = logging.WARNING - 10 * min(verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def _find_profile(_ctx: click.Context, _param: click.Parameter, path: Path) -> Path:
    """A relative profile path missing here is looked up in the checkout's folder too,
    so the defaults work from any directory."""
    if path.is_absolute() or path.exists():
        return path
    bundled = Path(__file__).resolve().parents[1] / path
    if not bundled.exists():
        return path  # the loader will say it is missing
    click.echo(f"note: {path} is not in {Path.cwd()}; using {bundled}", err=True)
    return bundled


_profile_opt = click.option(
    "--profile",
    "profile_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("vehicle_profiles/f450.yaml"),
    show_default=True,
    callback=_find_profile,
    help="Vehicle profile YAML (a relative path not found here is also looked up in "
    "the checkout, so vehicle_profiles/NAME.yaml works from any directory).",
)
_controller_opt = click.option(
    "--controller",
    "controller_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Controller config YAML (default: companion/data/mfc_default.yaml, or "
    "mfc_rates.yaml with --output rates; for every vehicle).",
)


def _load_inputs(
    profile_path: Path,
    controller_path: Path | None,
    output: str = "actuator",
    *,
    simulated: bool = False,
) -> tuple[Any, Any, Path]:
    from companion.config import default_controller, load_controller
    from companion.profile import load_profile

    ctrl_path = controller_path or default_controller(output)
    try:
        profile = load_profile(profile_path, simulated=simulated)
        cfg = load_controller(ctrl_path)
    except ConfigError as exc:
        _fail_config(exc)
    return profile, cfg, ctrl_path


@cli.command("check-config")
@_profile_opt
@_controller_opt
def check_config(profile_path: Path, controller_path: Path | None) -> None:
    """Validate a profile and a controller config; print the effective values."""
    from companion.config import build_mixer

    profile, cfg, ctrl_path = _load_inputs(profile_path, controller_path)
    mixer = build_mixer(profile)
    roll_f, pitch_f, yaw_f = mixer.factors()
    doc = {
        "profile": {"path": str(profile_path), **profile.model_dump(mode="json")},
        "controller": {"path": str(ctrl_path), **cfg.model_dump(mode="json")},
        "mixer": {"roll": roll_f, "pitch": pitch_f, "yaw": yaw_f, "idle": mixer.idle},
    }
    click.echo(json.dumps(doc, indent=2))


@cli.command("simulate")
@_profile_opt
@_controller_opt
@click.option("--scenario", default="paper-acro", show_default=True, help="Scenario name or file.")
@click.option("--seed", type=SEED, default=None, help="Override the scenario's seed.")
@click.option(
    "--controller-profile",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Give the controller this profile's geometry instead of the flown vehicle's.",
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    callback=usable_out_dir,
    default=Path("runs/latest"),
    show_default=True,
    help="Folder for metrics.json, plots, flight.npz and report.md.",
)
@click.option("--progress/--no-progress", default=True, show_default=True)
def simulate(
    profile_path: Path,
    controller_path: Path | None,
    scenario: str,
    seed: int | None,
    controller_profile: Path | None,
    out_dir: Path,
    progress: bool,
) -> None:
    """Fly a scenario in one process (plant + controller, no MAVLink) and write a report."""
    from companion.profile import load_profile
    from companion.report import write_report
    from companion.simulate import simulate_flight
    from sitl.scenario import load_scenario

    profile, cfg, ctrl_path = _load_inputs(profile_path, controller_path, simulated=True)
    try:
        sc = load_scenario(scenario)
        ctrl_prof = load_profile(controller_profile) if controller_profile else None
    except ConfigError as exc:
        _fail_config(exc)
    with _percent_bar(f"{sc.name} on {profile.name}", progress) as tick:
        record = simulate_flight(
            profile, cfg, sc, controller_profile=ctrl_prof, seed=seed, progress=tick
        )
    metrics = write_report(
        record,
        out_dir,
        controller_path=str(ctrl_path),
        profile_path=str(profile_path),
        scenario_desc=sc.description.strip(),
    )
    mae = metrics["mae_deg_s"]
    click.echo(
        f"{'CRASHED' if metrics['crashed'] else 'flew'} {metrics['sim_time_s']:.1f} s in "
        f"{metrics['wall_time_s']:.1f} s; MAE roll {mae['roll']} pitch {mae['pitch']} "
        f"yaw {mae['yaw']} deg/s; report: {out_dir / 'report.md'}"
    )


@cli.command("run")
@click.option(
    "--connect",
    default="udpin:0.0.0.0:14540",
    show_default=True,
    help="udpin:HOST:PORT, udpout:HOST:PORT or serial:DEVICE:BAUD.",
)
@_profile_opt
@_controller_opt
@click.option(
    "--output",
    type=click.Choice(["actuator", "rates"]),
    default="actuator",
    show_default=True,
    help="actuator: SET_ACTUATOR_CONTROL_TARGET (PX4 <= 1.13, bundled SITL); "
    "rates: SET_ATTITUDE_TARGET body rates (PX4 >= 1.14, ArduPilot).",
)
@click.option(
    "--engage",
    type=click.Choice(["auto", "rc-switch", "none"]),
    default="rc-switch",
    show_default=True,
    help="auto: OFFBOARD+arm (simulation); rc-switch: while an RC "
    "channel is high; none: shadow mode, sends no setpoint, mode or arm command.",
)
@click.option("--engage-channel", type=click.IntRange(5, 18), default=5, show_default=True)
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
@click.option(
    "--rate-hz",
    type=Finite(50.0, 1000.0),
    default=250.0,
    show_default=True,
    help="IMU stream (= control loop) rate requested from the autopilot.",
)
@click.option(
    "--log-dir",
    type=click.Path(file_okay=False),
    callback=usable_out_dir,
    default=None,
    help="Write flight.tlog, control.bin and events.jsonl here.",
)
@click.option("--mqtt", "mqtt_url", default=None, help="mqtt://HOST[:PORT]/PREFIX telemetry.")
@click.option(
    "--signing-key",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="MAVLink 2 signing key file (see docs/signing.md).",
)
@click.option(
    "--duration",
    type=Finite(min=0.0, min_open=True),
    default=None,
    help="Stop after this long engaged (sample time, s), handing back; in shadow mode "
    "(--engage none), after this long since the first sample.",
)
@click.option(
    "--on-failsafe",
    type=click.Choice(["exit", "wait"]),
    default="exit",
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
    default="auto",
    show_default=True,
    help="Mode handed back to. auto: a manual mode while valid RC is seen (not after RC "
    "loss), else hold with a position estimate, else land (PX4 posctl/altctl, hold, land; "
    "ArduPilot alt_hold, loiter, land). Named: PX4 posctl/altctl/stabilized/manual/hold/"
    "land; ArduPilot alt_hold/stabilize/loiter/brake/land (checked on connect); one whose "
    "needs are not met gives way to the pilot-free modes after it.",
)
@click.option(
    "--hand-back-watch-s",
    type=Finite(min=0.0),
    default=3.0,
    show_default=True,
    help="After a hand-back, watch the autopilot's mode this long: if it leaves the safe "
    "mode (its own failsafe) or never shows it, try the next one. 0: not watched.",
)
@click.option("--stale-imu-s", type=Finite(min=0.0, min_open=True), default=0.1, show_default=True)
@click.option(
    "--link-timeout-s",
    type=Finite(min=0.0, min_open=True),
    default=3.5,
    show_default=True,
    help="Failsafe when engaged and no autopilot heartbeat for this long (the default "
    "tolerates two lost 1 Hz heartbeats).",
)
@click.option(
    "--on-record-error",
    type=click.Choice(["continue", "failsafe"]),
    default="continue",
    show_default=True,
    help="A record file that cannot be written (disk full): log it and fly on, or also fail safe.",
)
@click.option(
    "--invalid-imu-s",
    type=Finite(min=0.0, min_open=True),
    default=0.05,
    show_default=True,
    help="Failsafe after this long of non-finite or out-of-range gyro samples.",
)
@click.option(
    "--rc-timeout-s",
    type=Finite(min=0.0, min_open=True),
    default=0.5,
    show_default=True,
    help="Failsafe when engaged and no valid RC for this long.",
)
@click.option(
    "--envelope-time-s",
    type=Finite(min=0.0, min_open=True),
    default=0.5,
    show_default=True,
    help="How long a rate beyond the profile's limit, or the averaging time of the "
    "tracking error, before the envelope failsafe.",
)
@click.option(
    "--autopilot-sysid",
    type=click.IntRange(1, 255),
    default=None,
    help="Listen only to this system [default: learnt from the first autopilot heartbeat].",
)
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
    type=Finite(min=0.0, min_open=True),
    default=10.0,
    show_default=True,
    help="How long to wait for the autopilot's first heartbeat (exit 1 after).",
)
@click.option(
    "--envelope-error-deg-s",
    type=Finite(min=0.0, min_open=True),
    default=300.0,
    show_default=True,
    help="Failsafe when the tracking error averaged over 0.5 s exceeds this.",
)
def run(
    connect: str,
    profile_path: Path,
    controller_path: Path | None,
    output: str,
    engage: str,
    engage_channel: int,
    rates_full_scale_deg_s: float,
    rates_lead_s: float,
    rates_passthrough: bool,
    imu_source: str,
    rate_hz: float,
    log_dir: Path | None,
    mqtt_url: str | None,
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
    envelope_time_s: float,
    autopilot_sysid: int | None,
    autopilot_compid: int | None,
    reference_path: Path | None,
    heartbeat_timeout_s: float,
    envelope_error_deg_s: float,
) -> None:
    """Fly the vehicle's rates with the controller over MAVLink."""
    import asyncio

    from companion.app import Companion, FailsafeConfig, RunOptions
    from companion.link.signing import load_signing_key
    from companion.link.transport import open_transport

    profile, cfg, ctrl_path = _load_inputs(profile_path, controller_path, output)
    # Check everything a run needs before anything is opened or sent.
    reference = None
    try:
        if rates_passthrough and output != "rates":
            raise ValueError(f"--rates-passthrough: needs --output rates (got --output {output})")
        if reference_path is not None:
            from companion.reference import load_reference

            reference = load_reference(reference_path)
        open_transport(connect)
        if mqtt_url:
            from companion.telemetry import MqttTelemetry

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
        moved = None
        if log_dir is not None:
            from companion.records import prepare_log_dir

            moved = prepare_log_dir(log_dir)
    except (ValueError, MfcError) as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(EXIT_BAD_INPUT)
    if moved is not None:
        click.echo(f"--log-dir {log_dir}: an earlier run's records moved to {moved}", err=True)
    opts = RunOptions(
        connect=connect,
        profile=profile,
        controller=cfg,
        # Absolute in the log's header, so `companion replay` finds them from anywhere.
        profile_path=str(Path(profile_path).resolve()),
        controller_path=str(Path(ctrl_path).resolve()),
        output=output,  # type: ignore[arg-type]
        engage=engage,  # type: ignore[arg-type]
        imu_source=imu_source,  # type: ignore[arg-type]
        loop_rate_hz=rate_hz,
        engage_channel=engage_channel,
        rates_passthrough=rates_passthrough,
        rates_full_scale_deg_s=rates_full_scale_deg_s,
        rates_lead_s=rates_lead_s,
        log_dir=log_dir,
        mqtt_url=mqtt_url,
        signing_key=signing_key,
        duration_s=duration,
        heartbeat_timeout_s=heartbeat_timeout_s,
        reference=reference,
        autopilot_sysid=autopilot_sysid,
        autopilot_compid=autopilot_compid,
        failsafe=FailsafeConfig(
            stale_imu_s=stale_imu_s,
            link_timeout_s=link_timeout_s,
            on_record_error=on_record_error,  # type: ignore[arg-type]
            invalid_imu_s=invalid_imu_s,
            rc_timeout_s=rc_timeout_s,
            envelope_time_s=envelope_time_s,
            tracking_error_max_deg_s=envelope_error_deg_s,
            on_failsafe=on_failsafe,  # type: ignore[arg-type]
            safe_mode=safe_mode,
            hand_back_watch_s=hand_back_watch_s,
        ),
    )
    sys.exit(asyncio.run(Companion(opts).run()))


@cli.command("fly")
@_profile_opt
@_controller_opt
@click.option("--scenario", default="paper-acro", show_default=True, help="Scenario name or file.")
@click.option("--seed", type=SEED, default=None, help="Override the scenario's seed.")
@click.option(
    "--output", type=click.Choice(["actuator", "rates"]), default="actuator", show_default=True
)
@click.option(
    "--duration",
    type=Finite(min=0.0, min_open=True),
    default=None,
    help="Engaged flight time, s [default: the scenario's].",
)
@click.option(
    "--controller-profile",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Give the companion this profile instead of the flown one.",
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    callback=usable_out_dir,
    default=Path("runs/fly"),
    show_default=True,
)
@click.option(
    "--autopilot",
    type=click.Choice(["px4", "ardupilot"]),
    default="px4",
    show_default=True,
    help="The SITL's personality; ardupilot implies --output rates.",
)
@click.option(
    "--compare-passthrough",
    is_flag=True,
    help="Rates output: fly the same scenario again sending the pilot's rates straight "
    "through (into OUT/passthrough) and report both.",
)
@click.option("--progress/--no-progress", default=True, show_default=True)
def fly(
    profile_path: Path,
    controller_path: Path | None,
    scenario: str,
    seed: int | None,
    output: str,
    duration: float | None,
    controller_profile: Path | None,
    out_dir: Path,
    autopilot: str,
    compare_passthrough: bool,
    progress: bool,
) -> None:
    """Fly a scenario: the SITL (lockstep) and the companion as two processes over UDP.

    Writes metrics.json, plots, report.md, and both processes' logs into OUT.
    """
    from companion.fly import FlightProcesses, fly_mavlink, merge_logs
    from companion.profile import load_profile
    from companion.report import write_report
    from companion.simulate import FlightRecord
    from sitl.scenario import load_scenario

    source = click.get_current_context().get_parameter_source("output")
    if autopilot == "ardupilot" and output == "actuator" and source == ParameterSource.COMMANDLINE:
        click.echo("error: --output actuator: ArduPilot accepts body rates only (--output rates)",
                   err=True)  # fmt: skip
        sys.exit(EXIT_BAD_INPUT)
    flown_output = "rates" if autopilot == "ardupilot" else output
    if compare_passthrough and flown_output != "rates":
        click.echo("error: --compare-passthrough needs --output rates (or --autopilot ardupilot)",
                   err=True)  # fmt: skip
        sys.exit(EXIT_BAD_INPUT)
    profile, _cfg, ctrl_path = _load_inputs(
        profile_path, controller_path, flown_output, simulated=True
    )
    try:
        sc = load_scenario(scenario)
        if controller_profile:
            load_profile(controller_profile)
    except ConfigError as exc:
        _fail_config(exc)
    meta = {"scenario": sc.name, "seed": sc.seed if seed is None else seed,
            "controller_profile": str(controller_profile or profile_path)}  # fmt: skip

    def fly_once(
        label: str, out: Path, companion_args: tuple[str, ...] = ()
    ) -> tuple[FlightProcesses, FlightRecord]:
        """One MAVLink flight of the scenario into ``out``, merged into a record."""
        with _percent_bar(f"{sc.name} on {profile.name}{label}", progress) as tick:
            fl = fly_mavlink(
                profile_path, scenario, out, controller_path=ctrl_path, output=output,
                duration_s=duration, seed=seed, controller_profile_path=controller_profile,
                autopilot=autopilot, companion_args=companion_args, progress=tick,
            )  # fmt: skip
        if not fl.control_log.exists():
            click.echo(
                f"error: the companion wrote no control log (exit {fl.companion_rc}); "
                f"see {out / 'companion.stderr'}",
                err=True,
            )
            sys.exit(1)
        return fl, merge_logs(fl, meta=meta)

    flight, record = fly_once(" (MAVLink)", out_dir)
    baseline = None
    if compare_passthrough:
        _, baseline = fly_once(", pass-through", out_dir / "passthrough", ("--rates-passthrough",))
    metrics = write_report(
        record,
        out_dir,
        controller_path=str(ctrl_path),
        profile_path=str(profile_path),
        scenario_desc=sc.description.strip(),
        passthrough=baseline,
    )
    mae = metrics["mae_deg_s"]
    click.echo(
        f"{'CRASHED' if metrics['crashed'] else 'flew'} {metrics['sim_time_s']:.1f} s in "
        f"{flight.wall_time_s:.1f} s wall; MAE roll {mae['roll']} pitch {mae['pitch']} "
        f"yaw {mae['yaw']} deg/s; report: {out_dir / 'report.md'}"
    )
    if baseline is not None:
        ptm = metrics["passthrough"]["mae_deg_s"]
        click.echo(
            f"pass-through: MAE roll {ptm['roll']} pitch {ptm['pitch']} yaw {ptm['yaw']} deg/s"
            f"{' (ended by a failsafe)' if metrics['passthrough']['failsafe_events'] else ''}"
        )
    if flight.companion_rc != 0:
        sys.exit(1)


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
    help="Write the replayed outputs here as a columnar log.",
)
def replay_cmd(
    log: Path, controller_path: Path | None, profile_path: Path | None, out_path: Path | None
) -> None:
    """Re-run a controller offline on a recorded control log (control.bin).

    With the recorded controller the outputs must match the log (a check that
    the flight was what the code says); with another controller they show what
    it would have commanded on the same samples (open loop).
    """
    from companion.config import DEFAULT_CONTROLLER, load_controller
    from companion.profile import load_profile
    from companion.records import ColumnarLog, read_columnar
    from companion.replay import compare, replay

    try:
        cols, meta = read_columnar(log)
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
        _fail_config(exc)
    out = replay(cols, cfg, profile)
    diffs = compare(cols, out)
    engaged = int((cols["engaged"] > 0.5).sum())
    click.echo(f"replayed {engaged} engaged samples of {log} with {ctrl} on {prof}")
    if "partial_last_row_bytes" in meta:
        click.echo(
            f"note: {log} ends in a partial row ({meta['partial_last_row_bytes']} bytes, "
            "ignored): its writer did not close it",
            err=True,
        )
    worst = max(diffs.values()) if diffs else 0.0
    for name, d in sorted(diffs.items(), key=lambda kv: -kv[1])[:8]:
        click.echo(f"  {name:24s} max |recorded - replayed| = {d:.3g}")
    click.echo(f"largest difference: {worst:.3g}")
    if out_path is not None:
        names = list(out)
        with ColumnarLog(
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


def _split_list(values: tuple[str, ...]) -> list[str]:
    return [v.strip() for item in values for v in item.split(",") if v.strip()]


@cli.command("campaign")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    callback=usable_out_dir,
    default=Path("runs/campaign"),
    show_default=True,
    help="Folder for campaign.json, summary.md and mae.png.",
)
@click.option(
    "--profiles",
    multiple=True,
    help="Profile names (vehicle_profiles/<name>.yaml) or files; repeat or comma-separate "
    "[default: every profile in vehicle_profiles/].",
)
@click.option(
    "--controllers",
    multiple=True,
    help="Controller files; repeat or comma-separate [default: the shipped MFC set and "
    "companion/data/pid_tarot_tuned.yaml].",
)
@click.option(
    "--damage",
    default="1.0,0.8,0.6",
    show_default=True,
    help="Motor 1 thrust/torque efficiency factors (comma-separated).",
)
@click.option(
    "--gusts", default="0,2", show_default=True, help="Wind gust sigmas, m/s (comma-separated)."
)
@click.option("--seeds", type=click.IntRange(min=1), default=3, show_default=True)
@click.option(
    "--seed-base",
    type=click.IntRange(min=0),
    default=1000,
    show_default=True,
    help="Seeds are seed-base .. seed-base + seeds - 1 (no tuning used these).",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=None,
    help="Parallel flights [default: os.cpu_count()].",
)
@click.option(
    "--duration",
    type=Finite(min=0.0, min_open=True),
    default=20.0,
    show_default=True,
    help="Fly only the first S seconds of the scenario.",
)
@click.option(
    "--scenario",
    default="train-acro",
    show_default=True,
    help="Scenario name or file. train-acro's pilot is seeded random acro, so each seed is "
    "a new flight of the kind both controllers were tuned for; paper-acro is the fixed test "
    "programme (reproduced by scripts/reproduce_paper.py).",
)
@click.option("--progress/--no-progress", default=True, show_default=True)
def campaign(
    out_dir: Path,
    profiles: tuple[str, ...],
    controllers: tuple[str, ...],
    damage: str,
    gusts: str,
    seeds: int,
    seed_base: int,
    workers: int | None,
    duration: float,
    scenario: str,
    progress: bool,
) -> None:
    """Fly a grid (profiles x damage x gusts x seeds x controllers) in parallel, in process.

    Default: 4 profiles x 3 damage x 2 gusts x 3 seeds x 2 controllers = 144 flights of
    20 s. For 200+ flights, e.g. --seeds 5 (240 flights) or --seeds 10 --duration 35
    (480 full train-acro flights).
    """
    import os
    import time
    from importlib.resources import files

    from companion.campaign import build_grid, run_campaign, write_outputs
    from companion.config import DEFAULT_CONTROLLER, load_controller
    from companion.profile import load_profile
    from sitl.scenario import load_scenario

    root = Path(__file__).resolve().parents[1]

    def profile_file(name: str) -> Path:
        p = Path(name)
        if p.suffix in (".yaml", ".yml") or p.exists():
            return p
        for base in (Path("vehicle_profiles"), root / "vehicle_profiles"):
            if (base / f"{name}.yaml").exists():
                return base / f"{name}.yaml"
        return Path("vehicle_profiles") / f"{name}.yaml"

    try:
        damages = [float(x) for x in _split_list((damage,))]
        gust_list = [float(x) for x in _split_list((gusts,))]
    except ValueError as exc:
        raise click.BadParameter(f"expected comma-separated numbers: {exc}") from exc
    if not damages or not gust_list:
        raise click.BadParameter("--damage and --gusts need at least one value each")
    if not all(0.0 < d <= 1.0 for d in damages):
        raise click.BadParameter(f"--damage: expected efficiencies in (0, 1], got {damage}")
    if not all(math.isfinite(g) and g >= 0.0 for g in gust_list):
        raise click.BadParameter(f"--gusts: expected finite sigmas >= 0 m/s, got {gusts}")
    prof_names, ctrl_names = _split_list(profiles), _split_list(controllers)
    for flag, given, names in (
        ("--profiles", profiles, prof_names),
        ("--controllers", controllers, ctrl_names),
    ):
        if given and not names:
            raise click.BadParameter(f"{flag}: expected names or files, got {list(given)!r}")
    if not prof_names:
        local = Path("vehicle_profiles")
        prof_dir = local if local.is_dir() else root / "vehicle_profiles"
        prof_names = [str(p) for p in sorted(prof_dir.glob("*.yaml"))]
    ctrl_files = ctrl_names or [
        str(DEFAULT_CONTROLLER),
        str(files("companion") / "data" / "pid_tarot_tuned.yaml"),
    ]
    try:
        prof = {Path(n).stem: load_profile(profile_file(n), simulated=True) for n in prof_names}
        ctrl = {Path(c).stem: load_controller(c) for c in ctrl_files}
        sc = load_scenario(scenario)
    except ConfigError as exc:
        _fail_config(exc)
    if len(ctrl) != len(ctrl_files) or len(prof) != len(prof_names):
        raise click.BadParameter("two profiles or two controllers share a file name")
    seed_list = list(range(seed_base, seed_base + seeds))
    try:
        specs = build_grid(
            prof, ctrl, sc, damages=damages, gusts_m_s=gust_list, seeds=seed_list,
            duration_s=duration,
        )  # fmt: skip
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from exc
    n_workers = workers or os.cpu_count() or 1
    _log.info("campaign: %d flights on %d workers", len(specs), n_workers)
    t0 = time.perf_counter()
    records = run_campaign(specs, workers=n_workers, progress=progress)
    meta = {
        "scenario": sc.name,
        "duration_s": duration,
        "profiles": list(prof),
        "controllers": {k: str(c) for k, c in zip(ctrl, ctrl_files, strict=True)},
        "damages": damages,
        "gusts_m_s": gust_list,
        "seeds": seed_list,
        "workers": n_workers,
        "flights": len(records),
        "wall_time_s": round(time.perf_counter() - t0, 1),
    }
    paths = write_outputs(records, out_dir, meta)
    crashes = sum(r["crashed"] for r in records)
    click.echo(
        f"{len(records)} flights ({crashes} crashed) in {meta['wall_time_s']:.0f} s; "
        f"summary: {paths['summary']}"
    )


@cli.command("envelope")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    callback=usable_out_dir,
    required=True,
    help="Folder for envelope.json, summary.md, ratio.png and worst-*.png.",
)
@click.option(
    "--n",
    type=click.IntRange(min=0),
    default=30,
    show_default=True,
    help="Latin-hypercube vehicles, on top of the named corners.",
)
@click.option(
    "--seed",
    type=SEED,
    default=1,
    show_default=True,
    help="Seeds the vehicle sample and every PID tuning search.",
)
@click.option("--corners-only", is_flag=True, help="Only the named corner vehicles.")
@click.option(
    "--damage/--no-damage",
    default=True,
    show_default=True,
    help="Add the motor60, imbalance and cg10 variants (the PID retuned on each).",
)
@click.option(
    "--damage-on",
    type=click.IntRange(min=0),
    default=8,
    show_default=True,
    help="How many vehicles get the damage variants: the first K, corners first.",
)
@click.option(
    "--tune-budget",
    type=click.IntRange(min=1),
    default=40,
    show_default=True,
    help="PID tuning flights per vehicle and case.",
)
@click.option(
    "--train-scenario",
    default="train-acro",
    show_default=True,
    help="Scenario the PID is tuned on (name or file).",
)
@click.option(
    "--test-scenario",
    default="envelope-test",
    show_default=True,
    help="Scenario every controller is scored on (name or file); never tuned on.",
)
@_controller_opt
@click.option(
    "--controller-profile",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("vehicle_profiles/f450.yaml"),
    show_default=True,
    callback=_find_profile,
    help="The profile MFC is given, whatever vehicle it flies.",
)
@click.option(
    "--worst",
    "worst_k",
    type=click.IntRange(min=0),
    default=3,
    show_default=True,
    help="How many worst cases to re-fly and plot.",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=None,
    help="Parallel cases [default: os.cpu_count()].",
)
@click.option("--progress/--no-progress", default=True, show_default=True)
def envelope(
    out_dir: Path,
    n: int,
    seed: int,
    corners_only: bool,
    damage: bool,
    damage_on: int,
    tune_budget: int,
    train_scenario: str,
    test_scenario: str,
    controller_path: Path | None,
    controller_profile: Path,
    worst_k: int,
    workers: int | None,
    progress: bool,
) -> None:
    """MFC (one file, never retuned) against a PID retuned for each envelope vehicle.

    Per vehicle and case: tunes the PID on the training scenario, then flies MFC (given
    the F450's profile), the tuned PID and PX4's default PID on the test scenario. Writes
    the ratio table, the envelope plot and the worst cases. Method: docs/envelope.md.
    """
    import os
    import time

    from companion.config import DEFAULT_CONTROLLER
    from companion.envelope import (
        envelope_cases,
        envelope_meta,
        load_setup,
        run_envelope,
        verdicts,
        write_envelope_outputs,
    )

    try:
        setup = load_setup(
            controller=controller_path,
            controller_profile=controller_profile,
            train_scenario=train_scenario,
            test_scenario=test_scenario,
            tune_budget=tune_budget,
            seed=seed,
        )
        cases = envelope_cases(
            n, seed, corners_only=corners_only, damage=damage, damage_on=damage_on
        )
    except ConfigError as exc:
        _fail_config(exc)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from exc
    n_workers = workers or os.cpu_count() or 1
    _log.info("envelope: %d cases on %d workers", len(cases), n_workers)
    t0 = time.perf_counter()
    records = run_envelope(cases, setup, workers=n_workers, progress=progress)
    meta = envelope_meta(
        cases,
        setup,
        seed=seed,
        n=n,
        corners_only=corners_only,
        mfc_controller=str(controller_path or DEFAULT_CONTROLLER),
        controller_profile=str(controller_profile),
        workers=n_workers,
        wall_time_s=round(time.perf_counter() - t0, 1),
    )
    paths = write_envelope_outputs(
        records, out_dir, meta, setup=setup, cases=cases, worst_k=worst_k
    )
    v = verdicts(records)["all"]
    click.echo(
        f"{len(records)} cases in {meta['wall_time_s']:.0f} s: MFC crashed in "
        f"{v['mfc_crashes']}; ratio target {'met' if v['ratio_within_target'] else 'not met'}; "
        f"better than PX4 default {'met' if v['better_than_default'] else 'not met'}; "
        f"summary: {paths['summary']}"
    )


def main() -> None:
    """Console-script entry point."""
    cli(prog_name="companion")


if __name__ == "__main__":
    main()
