"""The simulated RC pilot.

A pilot turns a timeline of desired body rates (deg/s) into RC frames, like a
person flying a multirotor in acro (body-rate) mode; the companion's rate
controller must track them.

* :mod:`sitl.pilot.rc` -- RC channel conventions and stick maths;
* :mod:`sitl.pilot.virtual` -- the virtual pilot's levelling and throttle laws;
* :mod:`sitl.pilot.scripted` -- the pilot that flies a timeline of segments;
* :mod:`sitl.pilot.maneuvers` -- the named maneuver library;
* :mod:`sitl.pilot.scripts` -- stick-script YAML files (format in its docstring);
* :mod:`sitl.pilot.factory` -- a pilot from a maneuver name or a file.
"""

from sitl.pilot.factory import make_pilot
from sitl.pilot.maneuvers import MANEUVERS
from sitl.pilot.rc import (
    DEFAULT_RATE_FULL_SCALE_DEG_S,
    Sticks,
    rate_to_stick_us,
    stick_us_to_rate,
    stick_us_to_throttle,
)
from sitl.pilot.scripted import Pilot, ScriptedPilot, Segment
from sitl.pilot.scripts import load_stick_script
from sitl.pilot.virtual import PilotParams, PilotView, level_rates_rad_s, throttle_command

__all__ = [
    "DEFAULT_RATE_FULL_SCALE_DEG_S",
    "MANEUVERS",
    "Pilot",
    "PilotParams",
    "PilotView",
    "ScriptedPilot",
    "Segment",
    "Sticks",
    "level_rates_rad_s",
    "load_stick_script",
    "make_pilot",
    "rate_to_stick_us",
    "stick_us_to_rate",
    "stick_us_to_throttle",
    "throttle_command",
]
