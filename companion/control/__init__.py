"""Pure control laws: no I/O, no clock, no messaging.

Everything here takes ``dt_s`` and samples from its caller and returns plain
values, so the same code runs against hardware, a real-time simulator or a
lockstep simulator at any speed.
"""

from companion.control.estimator import AlgebraicEstimator, WindowEstimator, make_estimator
from companion.control.mfc import (
    AlphaAdaptation,
    ControlOutput,
    IntelligentController,
    MfcAxisGains,
    MfcController,
    MfcGains,
    PidController,
    ReferencePrefilter,
)
from companion.control.mixer import Mixer, MixResult
from companion.control.pid import PX4_DEFAULT_GAINS, PidAxisGains, PidGains, RatePid
from companion.control.sticks import AxisRates, PilotCommand, StickMap

__all__ = [
    "PX4_DEFAULT_GAINS",
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
    "RatePid",
    "ReferencePrefilter",
    "StickMap",
    "WindowEstimator",
    "make_estimator",
]
