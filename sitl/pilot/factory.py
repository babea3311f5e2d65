"""Build a pilot from a maneuver name or a stick-script file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sitl.pilot.maneuvers import MANEUVERS
from sitl.pilot.scripted import Pilot, ScriptedPilot
from sitl.pilot.scripts import load_stick_script

__all__ = ["make_pilot"]


def make_pilot(
    spec: str,
    *,
    rng: np.random.Generator,
    free_flight: bool = True,
    aux_us: tuple[int, ...] = (),
) -> Pilot:
    """Build a pilot from a maneuver name or a stick-script file.

    Parameters
    ----------
    spec : str
        A key of :data:`MANEUVERS` (``"paper-acro"``, ``"roll-flip"``, ...) or a
        path to a stick-script YAML file.
    rng : numpy.random.Generator
        Randomness for the library's random details (all drawn here).
    free_flight : bool
        ``False`` for a test-stand rig: constant hover throttle, no altitude loop.
    aux_us : tuple of int
        ch5.. values for library maneuvers (e.g. ``(2000,)`` to hold an engage
        switch on); stick scripts set their own.

    Returns
    -------
    Pilot
        A :class:`ScriptedPilot`.

    Raises
    ------
    ValueError
        Unknown maneuver name that is not an existing file.
    companion.errors.ConfigError
        The stick-script file is invalid.
    """
    builder = MANEUVERS.get(spec)
    if builder is not None:
        segments, duration_s = builder(rng)
        return ScriptedPilot(
            segments, duration_s, free_flight=free_flight, aux_us=aux_us, name=spec
        )
    p = Path(spec)
    if p.suffix in (".yaml", ".yml") or p.exists():
        return load_stick_script(p, free_flight=free_flight)
    raise ValueError(
        f"unknown pilot {spec!r}: expected one of {sorted(MANEUVERS)} or a stick-script file"
    )
