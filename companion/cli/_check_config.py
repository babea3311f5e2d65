"""``companion check-config``: validate a profile and a controller config, print the
effective values, and with ``--fly`` fly the controller in the lab's simulator."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from companion.cli._shared import read_fly_check, warn_profile
from companion.errors import LabMissingError
from companion.lab import LAB_EXTRA, fly_check_flights
from companion.options import (
    EXIT_BAD_INPUT,
    WORKERS,
    controller_opt,
    load_inputs,
    profile_opt,
)

if TYPE_CHECKING:
    from companion.fly_check import FlyCheck

__all__ = ["check_config"]


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


@click.command("check-config")
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
    warn_profile(profile, profile_path)
    check = read_fly_check(ctrl_path)  # its hash before the flights
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
