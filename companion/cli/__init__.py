"""The ``companion`` command line.

The product's commands (``run``, ``preflight``, ``check-config``, ``replay``) are
this package's, one module each, added to the group here. The
lab's (``fly``, ``simulate``, ``campaign``, ``envelope``) and the flights of
``check-config --fly`` are the lab's own: found through the entry points it
registers (:mod:`companion.lab`) and loaded only when one of them is asked for, so
a companion computer's install needs neither the simulator nor its plotting.

Exit codes: 0 success, 1 a run that failed (e.g. crashed when asked to fail
on it), 2 bad input (a configuration error names the file and the field;
nothing is started).
"""

from __future__ import annotations

import logging

import click

from companion import __version__
from companion.cli._check_config import check_config
from companion.cli._preflight import preflight
from companion.cli._replay import REPLAY_TOLERANCE, replay_cmd
from companion.cli._run import run
from companion.errors import LabMissingError
from companion.lab import LAB_COMMANDS, LAB_EXTRA, lab_command

__all__ = ["REPLAY_TOLERANCE", "cli", "main"]

_log = logging.getLogger("companion")


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


cli.add_command(check_config)
cli.add_command(preflight)
cli.add_command(run)
cli.add_command(replay_cmd)


def main() -> None:
    """Console-script entry point."""
    cli(prog_name="companion")
