"""The ``companion`` command line.

Exit codes: 0 success, 1 a run that failed (e.g. crashed when asked to fail
on it), 2 bad input (a configuration error names the file and the field;
nothing is started).
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Any

import click

from companion import __version__
from companion.errors import ConfigError

__all__ = ["main"]

_log = logging.getLogger("companion")

EXIT_BAD_INPUT = 2


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


_profile_opt = click.option(
    "--profile",
    "profile_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("vehicle_profiles/f450.yaml"),
    show_default=True,
    help="Vehicle profile YAML.",
)
_controller_opt = click.option(
    "--controller",
    "controller_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Controller config YAML (default: the paper's Table I, shared by every vehicle).",
)


def _load_inputs(profile_path: Path, controller_path: Path | None) -> tuple[Any, Any, Path]:
    from companion.config import DEFAULT_CONTROLLER, load_controller
    from companion.profile import load_profile

    ctrl_path = controller_path or DEFAULT_CONTROLLER
    try:
        profile = load_profile(profile_path)
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
@click.option("--seed", type=int, default=None, help="Override the scenario's seed.")
@click.option(
    "--controller-profile",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Give the controller this profile's geometry instead of the flown vehicle's.",
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
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
    from tqdm import tqdm

    from companion.profile import load_profile
    from companion.report import write_report
    from companion.simulate import simulate_flight
    from sitl.scenario import load_scenario

    profile, cfg, ctrl_path = _load_inputs(profile_path, controller_path)
    try:
        sc = load_scenario(scenario)
        ctrl_prof = load_profile(controller_profile) if controller_profile else None
    except ConfigError as exc:
        _fail_config(exc)
    bar = tqdm(total=100, desc=f"{sc.name} on {profile.name}", unit="%", disable=not progress)
    done = [0]

    def tick(frac: float) -> None:
        n = int(frac * 100)
        if n > done[0]:
            bar.update(n - done[0])
            done[0] = n

    record = simulate_flight(
        profile, cfg, sc, controller_profile=ctrl_prof, seed=seed, progress=tick
    )
    bar.close()
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


def main() -> None:
    """Console-script entry point."""
    cli(prog_name="companion")


if __name__ == "__main__":
    main()
