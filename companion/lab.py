"""What the product finds of the lab: the entry points the lab registers.

The lab (``sitl.lab``: the bundled simulator's flights, campaigns and reports) is
not part of the product, and the product imports nothing of it by name. The lab
registers what it adds to the ``companion`` command line as entry points
(``pyproject.toml``, ``[project.entry-points]``), and the product looks them up by
group and name with :mod:`importlib.metadata`, loading one only when it is asked
for:

``mfc_companion.lab_commands``
    The ``companion`` subcommands the lab adds (:data:`LAB_COMMANDS`), each a
    :class:`click.Command`.
``mfc_companion.fly_check``
    ``flights``: the simulator flights of ``companion check-config --fly``, a
    :class:`FlyCheckFlights`.

An install without the lab (no such entry point, or its module does not import:
the simulator or the lab's libraries are missing) raises
:class:`~companion.errors.LabMissingError`, which says which extra brings it.
"""

from __future__ import annotations

from collections.abc import Sequence
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any, Protocol

from companion.errors import LabMissingError

if TYPE_CHECKING:
    import click

    from companion.config import MfcConfig, PidConfig

__all__ = [
    "COMMANDS_GROUP",
    "FLY_CHECK_GROUP",
    "LAB_COMMANDS",
    "LAB_EXTRA",
    "FlightVerdict",
    "FlyCheckFlights",
    "fly_check_flights",
    "lab_command",
]

COMMANDS_GROUP = "mfc_companion.lab_commands"
FLY_CHECK_GROUP = "mfc_companion.fly_check"

LAB_COMMANDS = ("campaign", "envelope", "fly", "simulate")
"""The lab's ``companion`` subcommands, by name: listed by ``companion --help``
whether or not this install has the lab, so that each can say what brings it."""

LAB_EXTRA = "pip install 'mfc-companion[lab]'"
"""What installs the project with its simulator and the lab's libraries."""


class FlightVerdict(Protocol):
    """One reference vehicle flown by ``check-config --fly``: its problems (none when
    it passed) and its record for the printed document."""

    @property
    def problems(self) -> tuple[str, ...]: ...

    def as_dict(self) -> dict[str, Any]: ...


class FlyCheckFlights(Protocol):
    """Fly a controller config on the reference vehicles; one verdict each, in order,
    the same for any number of ``workers`` (processes)."""

    def __call__(
        self, cfg: MfcConfig | PidConfig, *, workers: int = 1
    ) -> Sequence[FlightVerdict]: ...


def _load(group: str, name: str) -> Any:
    """The object the entry point ``name`` of ``group`` names, imported now."""
    found = entry_points(group=group, name=name)
    if not found:
        raise LabMissingError(f"no entry point {name!r} in group {group!r}")
    entry = next(iter(found))
    try:
        return entry.load()
    except ImportError as exc:
        raise LabMissingError(str(exc)) from exc


def lab_command(name: str) -> click.Command:
    """The lab's ``companion`` subcommand ``name`` (one of :data:`LAB_COMMANDS`)."""
    command: click.Command = _load(COMMANDS_GROUP, name)
    return command


def fly_check_flights() -> FlyCheckFlights:
    """The flights of ``companion check-config --fly``."""
    flights: FlyCheckFlights = _load(FLY_CHECK_GROUP, "flights")
    return flights
