"""The lab's commands: ``fly``, ``simulate``, ``campaign``, ``envelope``.

They are ``companion`` subcommands (the product's command line imports this
module only when one of them is asked for) and fly the bundled simulator, so
they need the ``lab`` extra (matplotlib for the plots, tqdm for progress).
Their flags, exit codes and ``metrics.json`` keys are contracts: extend them,
never rename. None overwrites an earlier run: what an earlier run wrote into
``--out`` is moved into ``earlier-<UTC time>/`` in it (after the arguments are
checked, before the work starts); ``campaign`` resumes an unfinished run of the
same grid instead.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import os
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import click
from click.core import ParameterSource

from companion.errors import ConfigError
from companion.options import (
    EXIT_BAD_INPUT,
    SEED,
    SIM_DURATION_MAX_S,
    WORKERS,
    Finite,
    controller_opt,
    fail_config,
    find_profile,
    keep_earlier,
    live_opt,
    load_inputs,
    mode_opt,
    output_opt,
    profile_opt,
    rates_law_axes_opt,
    usable_out_dir,
)
from companion.rate_loop import LawAxes
from sitl.cli import ENVELOPE_N_MAX
from sitl.lab.campaign_file import MAX_FLIGHTS
from sitl.link_model import LinkSpec
from sitl.scenario import GUST_SIGMA_MAX_M_S

__all__ = ["campaign", "envelope", "fly", "simulate"]

_log = logging.getLogger("companion")

_LAB_EXTRAS = ("matplotlib", "tqdm")
_CAMPAIGN_EXTRAS = ("distributed", "pyarrow")


def _need_lab_extras(more: tuple[str, ...] = ()) -> None:
    """Fail with the install command when the lab's libraries are missing."""
    missing = [m for m in (*_LAB_EXTRAS, *more) if importlib.util.find_spec(m) is None]
    if missing:
        raise click.ClickException(
            f"the lab needs {', '.join(missing)}: pip install 'mfc-companion[lab]'"
        )


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


_scenario_opt = click.option(
    "--scenario", default="paper-acro", show_default=True, help="Scenario name or file."
)
_seed_opt = click.option("--seed", type=SEED, default=None, help="Override the scenario's seed.")


def _parse_link(ctx: click.Context, param: click.Parameter, value: str | None) -> Any:
    if value is None:
        return None
    from sitl.link_model import parse_link

    try:
        return parse_link(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


_link_opt = click.option(
    "--link",
    default=None,
    callback=_parse_link,
    metavar="PROFILE|FIELDS",
    help="The companion link the flight goes through: ideal, ethernet, uart, usb-serial, "
    "wifi, or fields (delay_ms=10,jitter_ms=5,loss=0.01) [default: the scenario's].",
)
_progress_opt = click.option("--progress/--no-progress", default=True, show_default=True)
_oracle_opt = click.option(
    "--oracle",
    is_flag=True,
    help="Also fly the lab's oracle (sitl/lab/oracle.py: a law that knows the plant) on the "
    "same scenario, seed and link, in process, and add its MAE, the flight's ratio to it "
    "and, if the flight crashed, whether the oracle that may also set the collective "
    "crashes too (feasible: false) to metrics.json under 'oracle'.",
)


def _add_oracle(
    metrics: dict[str, Any], out_dir: Path, profile: Any, sc: Any, seed: int | None
) -> None:
    """Fly the oracle on the flight's scenario and add its figures to ``metrics.json``."""
    from sitl.lab.oracle import oracle_flight

    oracle = oracle_flight(profile, sc, seed=seed)
    mae, ref = metrics["mae_deg_s"], oracle["mae_deg_s"]
    feasible = True
    if metrics["crashed"]:
        feasible = not oracle_flight(profile, sc, seed=seed, collective=True)["crashed"]
    metrics["oracle"] = {
        "mae_deg_s": ref,
        "crashed": oracle["crashed"],
        "ratio": {a: round(mae[a] / ref[a], 3) if ref[a] else None for a in ref},
        "feasible": feasible,
    }
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n", encoding="utf-8")
    r = metrics["oracle"]["ratio"]
    click.echo(
        f"oracle: MAE roll {ref['roll']} pitch {ref['pitch']} yaw {ref['yaw']} deg/s; flight "
        f"over oracle {r['roll']} / {r['pitch']} / {r['yaw']}"
        + ("" if feasible else "; infeasible: the oracle with the collective crashes too")
    )


def _add_outer(
    metrics: dict[str, Any], out_dir: Path, flight: Any, mode: str, mission: Any
) -> None:
    """The outer loops' figures into ``metrics.json`` (``outer``), ``path.png`` and a
    section of ``report.md``."""
    from sitl.lab.outer_report import outer_metrics, plot_path

    outer = outer_metrics(flight, mode, mission)
    metrics["outer"] = outer
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n", encoding="utf-8")
    plot_path(flight, out_dir, mission, title=f"--mode {mode}")
    lines = ["", f"## Outer loops: `--mode {mode}`", "",
             f"Engaged {outer['engaged_s']} s, airborne {outer['airborne_s']} s."]  # fmt: skip
    m = outer.get("mission")
    if m is not None:
        lines.append(f"Mission: {m['reached']} of {m['waypoints']} waypoints reached.")
        pe = m.get("path_error_m")
        if pe:
            lines.append(
                f"Path error (true position to the planned legs, airborne): RMS {pe['rms']} m "
                f"(horizontal {pe['horizontal_rms']}, vertical {pe['vertical_rms']}), "
                f"max {pe['max']} m."
            )
    lines += ["", "![path](path.png)", ""]
    with (out_dir / "report.md").open("a", encoding="utf-8") as f:
        f.write("\n".join(lines))
    click.echo(
        f"outer ({mode}): airborne {outer['airborne_s']} s"
        + (
            f"; mission {m['reached']}/{m['waypoints']} waypoints, path error RMS "
            f"{m.get('path_error_m', {}).get('rms', '-')} m"
            if m is not None
            else ""
        )
    )


def _controller_profile_opt(help_: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    return click.option(
        "--controller-profile",
        type=click.Path(dir_okay=False, path_type=Path),
        default=None,
        help=help_,
    )


def _split_list(values: tuple[str, ...]) -> list[str]:
    return [v.strip() for item in values for v in item.split(",") if v.strip()]


def _parse_scheduler(ctx: click.Context, param: click.Parameter, value: str | None) -> Any:
    """``tcp://HOST:PORT`` (or ``tls://``); a bare ``HOST:PORT`` means tcp."""
    if value is None:
        return None
    from urllib.parse import urlsplit

    address = value.strip() if "://" in value else f"tcp://{value.strip()}"
    try:
        parts = urlsplit(address)
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme not in ("tcp", "tls") or not parts.hostname or port is None or parts.path:
        raise click.BadParameter(f"expected a scheduler address tcp://HOST:PORT, got {value!r}")
    return address


_scheduler_opt = click.option(
    "--scheduler",
    metavar="TCP_ADDRESS",
    default=None,
    callback=_parse_scheduler,
    help="Fly on a running Dask cluster (dask scheduler, dask worker with this project "
    "installed): its scheduler's address, tcp://HOST:8786 [default: worker processes on "
    "this machine].",
)


def _check_scheduler(scheduler: str) -> None:
    """Refuse ``--scheduler`` (exit 2) when no Dask scheduler answers there, before
    anything is moved or written."""
    from sitl.lab.executor import Executor

    try:
        with Executor(scheduler) as ex:
            click.echo(f"--scheduler {scheduler}: dashboard {ex.dashboard_link}", err=True)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--scheduler") from exc


@click.command("simulate")
@profile_opt
@controller_opt
@_scenario_opt
@_seed_opt
@_controller_profile_opt(
    "Give the controller this profile's geometry instead of the flown vehicle's."
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    callback=usable_out_dir,
    default=Path("runs/latest"),
    show_default=True,
    help="Folder for metrics.json, plots, flight.npz and report.md (an earlier run's are "
    "moved into earlier-<UTC time>/ in it first).",
)
@_link_opt
@_progress_opt
@_oracle_opt
@mode_opt(
    "Beyond rates: the outer loops (companion run --mode) on an outer scenario "
    "(--scenario one of angle-sticks, altitude-steps, position-hold, square, square-fast, "
    "figure-eight, figure-eight-fast; default: angle-sticks, altitude-steps or "
    "position-hold), on the autopilot's estimator model; metrics.json's key 'outer', "
    "path.png and report.md.",
)
def simulate(
    profile_path: Path,
    controller_path: Path | None,
    scenario: str,
    seed: int | None,
    controller_profile: Path | None,
    out_dir: Path,
    link: LinkSpec | None,
    progress: bool,
    oracle: bool,
    flight_mode: str,
) -> None:
    """Fly a scenario in one process (plant + controller, no MAVLink) and write a report."""
    _need_lab_extras()
    if flight_mode != "rates":
        _simulate_outer(
            profile_path, controller_path, scenario, seed, out_dir, flight_mode,
            refused={"--controller-profile": controller_profile is not None,
                     "--link": link is not None, "--oracle": oracle},
        )  # fmt: skip
        return
    from companion.profile import load_profile
    from sitl.lab.report import REPORT_FILES, write_report
    from sitl.lab.simulate import simulate_flight
    from sitl.scenario import load_scenario

    profile, cfg, ctrl_path = load_inputs(profile_path, controller_path, simulated=True)
    try:
        sc = load_scenario(scenario)
        ctrl_prof = load_profile(controller_profile) if controller_profile else None
    except ConfigError as exc:
        fail_config(exc)
    if link is not None:
        sc = sc.model_copy(update={"link": link})
    keep_earlier(f"--out {out_dir}", out_dir, (*REPORT_FILES, "control.mcap"))
    out_dir.mkdir(parents=True, exist_ok=True)
    with _percent_bar(f"{sc.name} on {profile.name}", progress) as tick:
        record = simulate_flight(
            profile, cfg, sc, controller_profile=ctrl_prof, seed=seed, progress=tick,
            control_log=out_dir / "control.mcap",
        )  # fmt: skip
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
        f"yaw {mae['yaw']} deg/s; report: {out_dir / 'report.md'}; control log: "
        f"{out_dir / 'control.mcap'}"
    )
    if oracle:
        _add_oracle(metrics, out_dir, profile, sc, seed)


def _simulate_outer(
    profile_path: Path,
    controller_path: Path | None,
    scenario: str,
    seed: int | None,
    out_dir: Path,
    mode: str,
    *,
    refused: dict[str, bool],
) -> None:
    """``companion simulate --mode angle|altitude|position``: one in-process outer flight."""
    from sitl.lab.outer_flight import (
        DEFAULT_SCENARIO,
        SCENARIOS,
        outer_metrics,
        simulate_outer_flight,
    )
    from sitl.lab.outer_report import OUTER_SIMULATE_FILES, write_outer_report

    for opt, given in refused.items():
        if given:
            raise click.UsageError(
                f"{opt}: not with --mode {mode} (the outer flights fly the "
                "ideal link, the rate loop on the flown vehicle's profile)"
            )
    ctx = click.get_current_context()
    if ctx.get_parameter_source("scenario") == ParameterSource.DEFAULT:
        scenario = DEFAULT_SCENARIO[mode]
    sc = SCENARIOS.get(scenario)
    if sc is None:
        raise click.BadParameter(
            f"{scenario!r}: with --mode {mode}, one of {', '.join(SCENARIOS)}",
            param_hint="--scenario",
        )
    if sc.mode != mode:
        raise click.BadParameter(
            f"{scenario} is a {sc.mode}-mode scenario, not {mode}", param_hint="--scenario"
        )
    profile, cfg, ctrl_path = load_inputs(profile_path, controller_path, simulated=True)
    keep_earlier(f"--out {out_dir}", out_dir, OUTER_SIMULATE_FILES)
    t0 = time.perf_counter()
    flight = simulate_outer_flight(profile, cfg, sc, seed=seed)
    figures = outer_metrics(flight, sc)
    write_outer_report(
        flight.columns, figures, out_dir, description=sc.description,
        controller_path=str(ctrl_path), profile_path=str(profile_path),
        wall_time_s=time.perf_counter() - t0,
    )  # fmt: skip
    h, path = figures.get("pos_rms_h_m"), figures.get("path_rms_m")
    click.echo(
        f"{'CRASHED' if figures['crashed'] else 'flew'} {sc.name} ({mode}); "
        + (f"position RMS {h:.2f} m horizontal, " if h is not None else "")
        + f"{figures['pos_rms_v_m']:.2f} m vertical"
        + (f", path error RMS {path:.2f} m" if path is not None else "")
        + f"; report: {out_dir / 'report.md'}"
    )


@click.command("fly")
@profile_opt
@controller_opt
@_scenario_opt
@_seed_opt
@output_opt
@click.option(
    "--duration",
    type=Finite(min=0.0, min_open=True, max=SIM_DURATION_MAX_S),
    default=None,
    help="Engaged flight time, s, at most an hour [default: the scenario's].",
)
@_controller_profile_opt("Give the companion this profile instead of the flown one.")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    callback=usable_out_dir,
    default=Path("runs/fly"),
    show_default=True,
    help="Folder for the report and both processes' logs (an earlier run's are moved "
    "into earlier-<UTC time>/ in it first).",
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
@rates_law_axes_opt
@mode_opt(
    "companion run --mode: what the pilot's sticks ask. Beyond rates, metrics.json "
    "gains 'outer' and the report path.png.",
)
@click.option(
    "--mission",
    "mission_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="With --mode position: companion run --mission FILE; metrics.json's outer.mission "
    "gives the path error against its plan.",
)
@_link_opt
@live_opt
@_progress_opt
@_oracle_opt
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
    rates_law_axes: LawAxes | None,
    flight_mode: str,
    mission_path: Path | None,
    link: LinkSpec | None,
    live: tuple[str, int] | None,
    progress: bool,
    oracle: bool,
) -> None:
    """Fly a scenario: the SITL (lockstep) and the companion as two processes over UDP.

    Writes metrics.json, plots, report.md, and both processes' logs into OUT.
    """
    _need_lab_extras()
    from companion.profile import load_profile
    from sitl.lab.fly import FLIGHT_FILES, FlightProcesses, fly_mavlink, merge_logs
    from sitl.lab.report import REPORT_FILES, write_report
    from sitl.lab.simulate import FlightRecord
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
    if rates_law_axes is not None and not all(rates_law_axes) and flown_output != "rates":
        click.echo("error: --rates-law-axes needs --output rates (or --autopilot ardupilot)",
                   err=True)  # fmt: skip
        sys.exit(EXIT_BAD_INPUT)
    profile, _cfg, ctrl_path = load_inputs(
        profile_path, controller_path, flown_output, simulated=True
    )
    if mission_path is not None and flight_mode != "position":
        click.echo(f"error: --mission: needs --mode position (got --mode {flight_mode})",
                   err=True)  # fmt: skip
        sys.exit(EXIT_BAD_INPUT)
    mission = None
    try:
        sc = load_scenario(scenario)
        if controller_profile:
            load_profile(controller_profile)
        if mission_path is not None:
            from companion.mission import load_mission

            mission = load_mission(mission_path)
    except ConfigError as exc:
        fail_config(exc)
    mode_args: tuple[str, ...] = () if flight_mode == "rates" else ("--mode", flight_mode)
    if mission_path is not None:
        mode_args += ("--mission", str(mission_path))
    if rates_law_axes is not None:
        from companion.step import law_axes_names

        mode_args += ("--rates-law-axes", law_axes_names(rates_law_axes))
    if live is not None:
        host, port = live
        mode_args += ("--live", f"[{host}]:{port}" if ":" in host else f"{host}:{port}")
    if link is not None:
        sc = sc.model_copy(update={"link": link})
    meta = {"scenario": sc.name, "seed": sc.seed if seed is None else seed,
            "controller_profile": str(controller_profile or profile_path),
            "link": sc.link.describe()}  # fmt: skip
    keep_earlier(
        f"--out {out_dir}", out_dir, (*FLIGHT_FILES, *REPORT_FILES, "passthrough", "path.png")
    )

    def fly_once(
        label: str, out: Path, companion_args: tuple[str, ...] = ()
    ) -> tuple[FlightProcesses, FlightRecord]:
        """One MAVLink flight of the scenario into ``out``, merged into a record."""
        with _percent_bar(f"{sc.name} on {profile.name}{label}", progress) as tick:
            fl = fly_mavlink(
                profile_path, scenario, out, controller_path=ctrl_path, output=output,
                duration_s=duration, seed=seed, controller_profile_path=controller_profile,
                autopilot=autopilot, companion_args=(*mode_args, *companion_args), progress=tick,
                link=sc.link,
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
    if flight_mode != "rates":
        _add_outer(metrics, out_dir, flight, flight_mode, mission)
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
    if oracle:
        flown = sc if duration is None else sc.model_copy(update={"duration_s": duration})
        _add_oracle(metrics, out_dir, profile, flown, seed)
    if flight.companion_rc != 0:
        sys.exit(1)


_GRID_OPTIONS = (
    "profiles", "controllers", "damage", "gusts", "seeds", "seed_base", "duration", "scenario",
    "oracle", "link",
)  # fmt: skip
"""The campaign's options a ``--grid`` file holds instead."""


@click.command("campaign")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    callback=usable_out_dir,
    default=Path("runs/campaign"),
    show_default=True,
    help="Folder for flights/ (one record per flight, written as it lands), "
    "flights.parquet, campaign.json, summary.md and mae.png. An unfinished run of the same "
    "grid there is resumed; a finished run's or another grid's outputs are moved into "
    "earlier-<UTC time>/ in it first.",
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
@click.option("--seeds", type=click.IntRange(min=1, max=MAX_FLIGHTS), default=3, show_default=True)
@click.option(
    "--seed-base",
    type=SEED,
    default=1000,
    show_default=True,
    help="Seeds are seed-base .. seed-base + seeds - 1 (no tuning used these).",
)
@click.option(
    "--workers",
    type=WORKERS,
    default=None,
    help="Parallel flights: local worker processes [default: os.cpu_count()]; with "
    "--scheduler, the cluster's workers fly instead.",
)
@_scheduler_opt
@click.option(
    "--duration",
    type=Finite(min=0.0, min_open=True, max=SIM_DURATION_MAX_S),
    default=20.0,
    show_default=True,
    help="Fly only the first S seconds of the scenario (at most an hour).",
)
@click.option(
    "--scenario",
    default="train-acro",
    show_default=True,
    help="Scenario name or file. train-acro's pilot is seeded random acro, so each seed is "
    "a new flight of the kind both controllers were tuned for; paper-acro is the fixed test "
    "programme (reproduced by scripts/reproduce_paper.py).",
)
@click.option(
    "--oracle/--no-oracle",
    default=True,
    show_default=True,
    help="Also fly the oracle (sitl/lab/oracle.py: a law that knows the plant) once per "
    "case: the limit each flight is read against (oracle_mae_* columns, ratios in "
    "summary.md).",
)
@_link_opt
@click.option(
    "--grid",
    "grid_file",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="A campaign file (YAML, docs/campaigns.md) that holds the whole grid: profiles, "
    "controllers, damage, gust sigmas, seeds, scenario, duration, oracle and link; the "
    "options for those are then not given. Flights are built as workers free up, so a "
    "grid of a million flights costs its axes in memory.",
)
@_progress_opt
@click.pass_context
def campaign(
    ctx: click.Context,
    out_dir: Path,
    profiles: tuple[str, ...],
    controllers: tuple[str, ...],
    damage: str,
    gusts: str,
    seeds: int,
    seed_base: int,
    workers: int | None,
    scheduler: str | None,
    duration: float | None,
    scenario: str,
    oracle: bool,
    link: LinkSpec | None,
    grid_file: Path | None,
    progress: bool,
) -> None:
    """Fly a grid (profiles x damage x gusts x seeds x controllers) in parallel, in process.

    Default: 4 profiles x 3 damage x 2 gusts x 3 seeds x 2 controllers = 144 flights of
    20 s. For 200+ flights, e.g. --seeds 5 (240 flights) or --seeds 10 --duration 35
    (480 full train-acro flights), or a campaign file (--grid FILE) for thousands.
    Flights run on Dask: worker processes here, or a cluster's with --scheduler.
    Killed, the same command resumes (docs/campaigns.md).
    """
    _need_lab_extras(_CAMPAIGN_EXTRAS)
    from companion.config import DEFAULT_CONTROLLER, load_controller
    from companion.profile import load_profile
    from sitl.lab.campaign import CAMPAIGN_FILES, Grid, run_campaign, write_outputs
    from sitl.lab.campaign_file import (
        MAX_FLIGHTS,
        load_campaign_file,
        resolve_controller,
        resolve_profile,
    )
    from sitl.lab.campaign_store import (
        RUN_FILES,
        CampaignStore,
        can_resume,
        flight_ids,
        grid_digest,
    )
    from sitl.lab.executor import Executor
    from sitl.link_model import parse_link
    from sitl.scenario import load_scenario

    root = Path(__file__).resolve().parents[2]
    base: Path | None = None
    seed_list: range | list[int]
    if grid_file is not None:
        given = [
            f"--{name.replace('_', '-')}"
            for name in _GRID_OPTIONS
            if ctx.get_parameter_source(name) == ParameterSource.COMMANDLINE
        ]
        if given:
            raise click.BadParameter(
                f"{grid_file} holds the grid: drop {', '.join(given)}", param_hint="--grid"
            )
        try:
            cf = load_campaign_file(grid_file)
        except ConfigError as exc:
            fail_config(exc)
        base = grid_file.parent
        prof_names, ctrl_names = list(cf.profiles or ()), list(cf.controllers or ())
        damages, gust_list, seed_list = cf.damage, cf.gust_sigma_m_s, cf.seed_values()
        duration, oracle = cf.duration_s, cf.oracle
        scenario = str(base / cf.scenario) if (base / cf.scenario).is_file() else cf.scenario
        link = parse_link(cf.link) if cf.link else None
    else:
        try:
            damages = [float(x) for x in _split_list((damage,))]
            gust_list = [float(x) for x in _split_list((gusts,))]
        except ValueError as exc:
            raise click.BadParameter(f"expected comma-separated numbers: {exc}") from exc
        if not damages or not gust_list:
            raise click.BadParameter("--damage and --gusts need at least one value each")
        if not all(0.0 < d <= 1.0 for d in damages):
            raise click.BadParameter(f"--damage: expected efficiencies in (0, 1], got {damage}")
        if not all(0.0 <= g <= GUST_SIGMA_MAX_M_S for g in gust_list):  # nan fails too
            raise click.BadParameter(
                f"--gusts: expected finite sigmas in 0..{GUST_SIGMA_MAX_M_S:g} m/s, got {gusts}"
            )
        prof_names, ctrl_names = _split_list(profiles), _split_list(controllers)
        for flag, given_raw, names in (
            ("--profiles", profiles, prof_names),
            ("--controllers", controllers, ctrl_names),
        ):
            if given_raw and not names:
                raise click.BadParameter(
                    f"{flag}: expected names or files, got {list(given_raw)!r}"
                )
        seed_list = range(seed_base, seed_base + seeds)
    if not prof_names:
        local = Path("vehicle_profiles")
        prof_dir = local if local.is_dir() else root / "vehicle_profiles"
        prof_names = [str(p.resolve()) for p in sorted(prof_dir.glob("*.yaml"))]
    ctrl_files = [resolve_controller(c, base) for c in ctrl_names] or [
        str(DEFAULT_CONTROLLER),
        resolve_controller("pid_tarot_tuned"),
    ]
    try:
        prof = {
            Path(n).stem: load_profile(resolve_profile(n, base), simulated=True) for n in prof_names
        }
        ctrl = {Path(c).stem: load_controller(c) for c in ctrl_files}
        sc = load_scenario(scenario)
    except ConfigError as exc:
        fail_config(exc)
    if link is not None:
        sc = sc.model_copy(update={"link": link})
    if len(ctrl) != len(ctrl_files) or len(prof) != len(prof_names):
        raise click.BadParameter("two profiles or two controllers share a file name")
    specs = Grid(
        prof, ctrl, sc, damages=damages, gusts_m_s=gust_list, seeds=seed_list,
        duration_s=duration,
    )  # fmt: skip
    if len(specs) > MAX_FLIGHTS:
        raise click.BadParameter(
            f"the grid is {len(specs):,} flights, over {MAX_FLIGHTS:,}",
            param_hint="--grid" if grid_file else "--seeds",
        )
    ids = flight_ids(specs)
    grid = grid_digest(ids)
    t0 = time.perf_counter()
    n_workers = min(workers or os.cpu_count() or 1, len(specs))
    with contextlib.ExitStack() as stack:
        try:
            executor = stack.enter_context(Executor(scheduler, n_workers))
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="--scheduler") from exc
        if scheduler is not None:
            n_workers = executor.threads()
            click.echo(f"--scheduler {scheduler}: dashboard {executor.dashboard_link}", err=True)
        store = CampaignStore(out_dir)
        if can_resume(out_dir, grid):
            done = len(store.flights(ids))
            click.echo(f"resuming: {done} of {len(specs)} flights done", err=True)
        else:
            keep_earlier(f"--out {out_dir}", out_dir, (*CAMPAIGN_FILES, *RUN_FILES))
            done = 0
        store.start(grid, len(specs))
        _log.info("campaign: %d flights on %d workers", len(specs) - done, n_workers)
        records = run_campaign(
            specs, progress=progress, executor=executor, store=store, oracle=oracle
        )
    meta = {
        "scenario": sc.name,
        "duration_s": duration,
        "profiles": list(prof),
        "controllers": {k: str(c) for k, c in zip(ctrl, ctrl_files, strict=True)},
        "damages": damages,
        "gusts_m_s": gust_list,
        "seeds": list(seed_list),
        "grid_file": str(grid_file) if grid_file else None,
        "workers": n_workers,
        "scheduler": scheduler or "local",
        "flights": len(records),
        "flown_this_run": len(specs) - done,
        "resumed_flights": done,
        "oracle": oracle,
        "wall_time_s": round(time.perf_counter() - t0, 1),
    }
    paths = write_outputs(records, out_dir, meta)
    crashes = sum(r["crashed"] is True for r in records)
    errors = sum(r["error"] is not None for r in records)
    click.echo(
        f"{len(records)} flights ({crashes} crashed"
        + (f", {errors} raised" if errors else "")
        + f") in {meta['wall_time_s']:.0f} s; summary: {paths['summary']}"
    )


@click.command("envelope")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    callback=usable_out_dir,
    required=True,
    help="Folder for envelope.json, envelope.parquet, summary.md, ratio.png and worst-*.png "
    "(an earlier run's are moved into earlier-<UTC time>/ in it first).",
)
@click.option(
    "--n",
    type=click.IntRange(min=0, max=ENVELOPE_N_MAX),
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
    type=click.IntRange(min=0, max=ENVELOPE_N_MAX),
    default=8,
    show_default=True,
    help="How many vehicles get the damage variants: the first K, corners first.",
)
@click.option(
    "--tune-budget",
    type=click.IntRange(min=1, max=10_000),
    default=40,
    show_default=True,
    help="PID tuning flights per vehicle and case (at most ten thousand).",
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
@controller_opt
@click.option(
    "--controller-profile",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("vehicle_profiles/f450.yaml"),
    show_default=True,
    callback=find_profile,
    help="The profile MFC is given, whatever vehicle it flies.",
)
@click.option(
    "--worst",
    "worst_k",
    type=click.IntRange(min=0, max=1000),
    default=3,
    show_default=True,
    help="How many worst cases to re-fly and plot.",
)
@click.option(
    "--workers",
    type=WORKERS,
    default=None,
    help="Parallel cases [default: os.cpu_count()].",
)
@_scheduler_opt
@_link_opt
@_progress_opt
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
    scheduler: str | None,
    link: LinkSpec | None,
    progress: bool,
) -> None:
    """MFC (one file, never retuned) against a PID retuned for each envelope vehicle.

    Per vehicle and case: tunes the PID on the training scenario, then flies MFC (given
    the F450's profile), the tuned PID and PX4's default PID on the test scenario. Writes
    the ratio table, the envelope plot and the worst cases. Method: docs/research/envelope.md.
    """
    _need_lab_extras()

    from companion.config import DEFAULT_CONTROLLER
    from sitl.lab.envelope import (
        ENVELOPE_FILES,
        envelope_meta,
        run_envelope,
        write_envelope_outputs,
    )
    from sitl.lab.envelope_setup import envelope_cases, load_setup
    from sitl.lab.envelope_verdicts import verdicts

    try:
        setup = load_setup(
            controller=controller_path,
            controller_profile=controller_profile,
            train_scenario=train_scenario,
            test_scenario=test_scenario,
            tune_budget=tune_budget,
            seed=seed,
            link=link,
        )
        cases = envelope_cases(
            n, seed, corners_only=corners_only, damage=damage, damage_on=damage_on
        )
    except ConfigError as exc:
        fail_config(exc)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from exc
    from sitl.lab.campaign_store import CampaignStore, grid_digest
    from sitl.lab.envelope import CASES_DIR, RUN_MANIFEST, case_ids

    if scheduler is not None:
        _check_scheduler(scheduler)
    ids = case_ids(cases, setup)
    grid = grid_digest(ids)
    store = CampaignStore(out_dir, manifest=RUN_MANIFEST, finished="envelope.json")
    if store.can_resume(grid):
        done = len(store.load(CASES_DIR, ids))
        click.echo(f"resuming: {done} of {len(cases)} cases done", err=True)
    else:
        keep_earlier(f"--out {out_dir}", out_dir, (*ENVELOPE_FILES, RUN_MANIFEST, CASES_DIR))
    store.start(grid, len(cases))
    n_workers = workers or os.cpu_count() or 1
    _log.info("envelope: %d cases on %d workers", len(cases), n_workers)
    t0 = time.perf_counter()
    records = run_envelope(
        cases, setup, workers=n_workers, progress=progress, scheduler=scheduler, store=store
    )
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
