"""Pure control laws: no I/O, no clock, no messaging.

Everything here takes ``dt_s`` and samples from its caller and returns plain
values, so the same code runs against hardware, a real-time simulator or a
lockstep simulator at any speed.

The modules are compiled with mypyc when installed from a wheel built where a
C compiler and the Python headers are present (``setup.py``); :data:`COMPILED`
says whether they were, :data:`CORE` says which core runs and, for the pure
one, why (for ``companion preflight`` and a person). An extension whose
source has changed since it was built is refused here, before it is imported:
flying yesterday's control law while reading today's is not an option.
"""

# First, so its check runs before any control module is imported (a submodule
# imported directly imports this package first).
from companion.control._compiled import COMPILED, CORE
from companion.control.estimator import AlgebraicEstimator, WindowEstimator, make_estimator
from companion.control.identifier import MAX_DELAY_S, AlphaAdaptation
from companion.control.intelligent import IntelligentController, MfcAxisGains
from companion.control.mfc import (
    ControlOutput,
    MfcController,
    MfcGains,
    PidController,
    RateController,
)
from companion.control.mixer import Mixer, MixResult
from companion.control.pid import PidAxisGains, PidGains, RatePid
from companion.control.prefilter import ReferencePrefilter
from companion.control.sticks import AxisRates, PilotCommand, StickMap

__all__ = [
    "AXES",
    "COMPILED",
    "CORE",
    "MAX_DELAY_S",
    "AlgebraicEstimator",
    "AlphaAdaptation",
    "AxisRates",
    "ControlOutput",
    "IntelligentController",
    "MfcAxisGains",
    "MfcController",
    "MfcGains",
    "MixResult",
    "Mixer",
    "PidAxisGains",
    "PidController",
    "PidGains",
    "PilotCommand",
    "RateController",
    "RatePid",
    "ReferencePrefilter",
    "StickMap",
    "WindowEstimator",
    "make_estimator",
]

AXES = ("roll", "pitch", "yaw")
"""The order of every per-axis triple (body frame FRD: x, y, z)."""
