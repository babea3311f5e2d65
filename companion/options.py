"""Command-line options and value types shared by ``companion``, its lab commands and ``sitl``.

click's ``FloatRange`` lets ``nan`` through every bound (it compares false with
anything) and ``inf`` past an open end; a watchdog given ``--stale-imu-s nan``
would never fire. :class:`Finite` closes that. Every number a command takes has
both ends: a value no user needs (``--duration 1e308``) is refused with click's
message naming the option, exit 2, before anything starts; the constants below
hold the ends several commands share. :func:`usable_out_dir` checks an
output folder before any work starts (making it and a file in it, then undoing
that), so a bad ``--out`` fails at once rather than after a long run.
:func:`keep_earlier` moves an earlier run's outputs aside before a command
writes its own: no command overwrites one.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, NoReturn

import click

from companion.errors import EXIT_BAD_INPUT, ConfigError
from companion.rate_loop import LawAxes

__all__ = [
    "EXIT_BAD_INPUT",
    "RUN_DURATION_MAX_S",
    "SEED",
    "SIM_DURATION_MAX_S",
    "WORKERS",
    "Finite",
    "argparse_type",
    "controller_opt",
    "fail_config",
    "keep_earlier",
    "live_opt",
    "load_inputs",
    "out_dir_problem",
    "output_opt",
    "profile_opt",
    "rates_law_axes_opt",
    "signing_key_opt",
    "usable_out_dir",
    "usable_out_file",
]

SEED = click.IntRange(min=0, max=2**32 - 1)
"""A seed: numpy's generators take a non-negative integer; below 2**32 as a
campaign file's seeds (``sitl.lab.campaign_file``) and numpy's legacy seeds are."""

WORKERS = click.IntRange(min=1, max=1024)
"""Worker processes on this machine: more than any one machine has cores."""

RUN_DURATION_MAX_S = 7 * 24 * 3600.0
"""``companion run --duration``: a week. A battery flight lasts under an hour; a
tethered multirotor flies for days; nothing flies longer unattended."""

SIM_DURATION_MAX_S = 3600.0
"""A simulated flight's ``--duration``: an hour, the longest a scenario may be
(``sitl.scenario``); the lab and ``sitl run --log`` keep every step in memory."""


class Finite(click.FloatRange):
    """A ``click.FloatRange`` whose value must also be a finite number."""

    name = "finite float range"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        # Finite first: "inf is not a finite number" says more than "not in the range".
        number = click.FLOAT.convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return super().convert(number, param, ctx)


def argparse_type(param_type: click.ParamType[Any, Any]) -> Callable[[str], Any]:
    """A click type (a :class:`Finite` range, :data:`SEED`) as an argparse ``type=``,
    so the scripts' numbers have the same ends and messages as the commands'."""

    def convert(text: str) -> Any:
        try:
            return param_type.convert(text, None, None)
        except click.BadParameter as exc:
            raise argparse.ArgumentTypeError(exc.message) from None

    convert.__name__ = param_type.name  # argparse names the type in its own messages
    return convert


def out_dir_problem(value: str | Path) -> str | None:
    """Why ``value`` cannot be an output folder, or None if it can: the folder
    exists or can be made, and a file can be written in it. Checked by doing it
    (making the missing folders and a temporary file), then undone, so nothing
    is left behind if the command stops before it starts its work."""
    if isinstance(value, str) and not value.strip():
        return "expected a folder path, got an empty one"
    path = Path(value)
    made: list[Path] = []
    try:
        missing = []
        p = Path(os.path.abspath(path))  # with any ".." resolved, as mkdir -p would
        while not p.exists():
            if p.is_symlink():
                return f"cannot create the folder {path}: {p} is a broken symlink"
            missing.append(p)
            p = p.parent
        if not p.is_dir():
            return f"cannot create the folder {path}: {p} is not a folder"
        for d in reversed(missing):
            d.mkdir()
            made.append(d)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:  # PermissionError from exists() in a folder we cannot enter
        return f"cannot create the folder or write in {path}: {exc.strerror or exc}"
    finally:
        for d in reversed(made):
            with contextlib.suppress(OSError):
                d.rmdir()
    return None


def usable_out_dir(
    ctx: click.Context, param: click.Parameter, value: str | Path | None
) -> Path | None:
    """A click callback for a ``click.Path(file_okay=False)`` option: see
    :func:`out_dir_problem`."""
    if value is None:
        return None
    problem = out_dir_problem(value)
    if problem is not None:
        raise click.BadParameter(problem, ctx, param)
    return Path(value)


def usable_out_file(
    ctx: click.Context, param: click.Parameter, value: str | Path | None
) -> Path | None:
    """A click callback for an output file option: not empty, not a folder, and
    its folder passes :func:`usable_out_dir`."""
    if value is None:
        return None
    if isinstance(value, str) and not value.strip():
        raise click.BadParameter("expected a file path, got an empty one", ctx, param)
    path = Path(value)
    if path.is_dir() or str(value).endswith(("/", ".")):
        raise click.BadParameter(f"{value} is a folder; expected a file path", ctx, param)
    usable_out_dir(ctx, param, path.parent)
    return path


def keep_earlier(what: str, folder: Path, names: Iterable[str]) -> None:
    """Before a command writes: its earlier outputs ``names`` in ``folder`` moved,
    untouched, into ``folder/earlier-<UTC time>/`` (:func:`companion.records.move_earlier`),
    and said so on stderr. ``what`` names the option (``--out runs/x``). Exits with
    :data:`EXIT_BAD_INPUT`, nothing started, if they cannot be moved."""
    from companion.records import move_earlier

    try:
        moved = move_earlier(folder, names, what=what)
    except ValueError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(EXIT_BAD_INPUT)
    if moved is not None:
        click.echo(f"{what}: an earlier run's outputs moved to {moved}", err=True)


def fail_config(exc: ConfigError) -> NoReturn:
    """Say what is wrong with the input and exit with :data:`EXIT_BAD_INPUT`."""
    click.echo(f"error: {exc}", err=True)
    sys.exit(EXIT_BAD_INPUT)


def find_profile(_ctx: click.Context, _param: click.Parameter, path: Path) -> Path:
    """A relative profile path missing here is looked up in the checkout's folder too,
    so the defaults work from any directory."""
    if path.is_absolute() or path.exists():
        return path
    bundled = Path(__file__).resolve().parents[1] / path
    if not bundled.exists():
        return path  # the loader will say it is missing
    click.echo(f"note: {path} is not in {Path.cwd()}; using {bundled}", err=True)
    return bundled


profile_opt = click.option(
    "--profile",
    "profile_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("vehicle_profiles/f450.yaml"),
    show_default=True,
    callback=find_profile,
    help="Vehicle profile YAML (a relative path not found here is also looked up in "
    "the checkout, so vehicle_profiles/NAME.yaml works from any directory).",
)
controller_opt = click.option(
    "--controller",
    "controller_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Controller config YAML (default: companion/data/mfc_default.yaml, or "
    "mfc_rates.yaml with --output rates; for every vehicle).",
)


def load_inputs(
    profile_path: Path,
    controller_path: Path | None,
    output: str = "actuator",
    *,
    simulated: bool = False,
) -> tuple[Any, Any, Path]:
    """The profile and the controller config (the shipped one when none is given);
    bad input exits with :data:`EXIT_BAD_INPUT`."""
    from companion.config import default_controller, load_controller
    from companion.profile import load_profile

    ctrl_path = controller_path or default_controller(output)
    try:
        profile = load_profile(profile_path, simulated=simulated)
        cfg = load_controller(ctrl_path)
    except ConfigError as exc:
        fail_config(exc)
    return profile, cfg, ctrl_path


output_opt = click.option(
    "--output",
    type=click.Choice(["actuator", "rates"]),
    default="actuator",
    show_default=True,
    help="actuator: SET_ACTUATOR_CONTROL_TARGET (PX4 <= 1.13, bundled SITL); "
    "rates: SET_ATTITUDE_TARGET body rates (PX4 >= 1.14, ArduPilot).",
)


FLIGHT_MODE_NAMES = ("rates", "angle", "altitude", "position")
"""``--mode``: what the pilot's sticks ask (docs/flying.md); each is a
:class:`companion.modes.FlightMode` (kept here as names: the command line is
read before the laws are imported)."""


def mode_opt(help_: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``--mode rates|angle|altitude|position`` (the parameter ``flight_mode``)."""
    return click.option(
        "--mode",
        "flight_mode",
        type=click.Choice(FLIGHT_MODE_NAMES),
        default="rates",
        show_default=True,
        help=help_,
    )


def signing_key_opt(help_: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``--signing-key FILE``: a MAVLink 2 signing key (docs/signing.md)."""
    return click.option(
        "--signing-key",
        type=click.Path(dir_okay=False, path_type=Path),
        default=None,
        help=help_,
    )


def _live_address(
    ctx: click.Context, param: click.Parameter, value: str | None
) -> tuple[str, int] | None:
    """``--live [HOST:]PORT`` as ``(host, port)``, once the SDK is known to be installed."""
    if value is None:
        return None
    from companion.live import parse_live_address, sdk_problem

    try:
        address = parse_live_address(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc), ctx, param) from None
    problem = sdk_problem()
    if problem is not None:
        raise click.BadParameter(problem, ctx, param)
    return address


live_opt = click.option(
    "--live",
    metavar="[HOST:]PORT",
    callback=_live_address,
    default=None,
    help="Serve the control log's topics live over the Foxglove WebSocket protocol "
    "(open ws://HOST:PORT in Foxglove; needs the live extra). HOST defaults to 127.0.0.1, "
    "this computer only; 0.0.0.0 serves every network it is on, the vehicle's too.",
)


def _law_axes(_ctx: click.Context, param: click.Parameter, value: str) -> LawAxes | None:
    """``--rates-law-axes``: ``auto`` (None), or a comma-separated set of roll, pitch
    and yaw, per axis whether it is in it."""
    from companion.step import law_axes_named

    if value == "auto":
        return None
    try:
        return law_axes_named(value)
    except ValueError as exc:
        raise click.BadParameter(f"{exc}, or 'auto'", param=param) from None


rates_law_axes_opt = click.option(
    "--rates-law-axes",
    callback=_law_axes,
    default="auto",
    show_default=True,
    help="With --output rates: the axes whose rate the law corrects, comma-separated; the "
    "others are sent the pilot's rate and the lead. 'auto': yaw always, roll and pitch "
    "unless the autopilot's rate gains there are 1.5 times its defaults or more, read at "
    "start-up (PX4's MC_*RATE_K times MC_*RATE_P; docs/controller.md).",
)
