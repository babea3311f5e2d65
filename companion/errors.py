"""The companion's error tree.

::

    MfcError
    ├── ConfigError (also ValueError)  bad profile or controller file
    ├── LinkError                      the MAVLink transport failed or was closed
    │   └── SigningError               a signing key file is unusable
    ├── EngageError                    the autopilot refused engagement (ACK denied, timeout)
    ├── LogDirInUseError               another run holds the --log-dir (its lock)
    └── LabMissingError                this install has no lab (a lab command, check-config --fly)

A simulated flight's outcome (landed, crashed, failsafe) is a value, not an exception.

The exit codes of the ``companion`` commands are here too: 0 success, 1 an
error (a run that could not start or engage), 2 bad input (nothing started),
3 a failsafe ended the run.
"""

from __future__ import annotations

__all__ = [
    "EXIT_BAD_INPUT",
    "EXIT_ERROR",
    "EXIT_FAILSAFE",
    "EXIT_OK",
    "ConfigError",
    "EngageError",
    "LabMissingError",
    "LinkError",
    "LogDirInUseError",
    "MfcError",
    "SigningError",
]

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_BAD_INPUT = 2
EXIT_FAILSAFE = 3


class MfcError(Exception):
    """Base of every error this package raises on purpose."""


class ConfigError(MfcError, ValueError):
    """A configuration file is unreadable or invalid.

    The message names the file, the key path and what was expected, e.g.
    ``vehicle_profiles/f450.yaml: physics.mass_kg: expected a number > 0, got -1.5``.
    """

    def __init__(self, path: str, problems: list[str]) -> None:
        self.path = path
        self.problems = list(problems)
        lines = "\n".join(f"  {p}" for p in self.problems)
        super().__init__(f"{path}: invalid configuration\n{lines}")


class LinkError(MfcError):
    """The MAVLink transport failed or was closed."""


class SigningError(LinkError):
    """A MAVLink 2 signing key file is missing or malformed."""


class EngageError(MfcError):
    """The autopilot refused or did not answer a step of engagement."""


class LogDirInUseError(MfcError):
    """Another run holds the ``--log-dir`` (its lock); the message names the folder and its pid."""


class LabMissingError(MfcError):
    """This install has no lab (:mod:`companion.lab`): the entry point the lab registers
    is absent or its module does not import; the message says which, or why."""
