"""``companion preflight``: is this autopilot set up for the companion to fly it?

Connects, sends nothing that moves the vehicle (HEARTBEAT, parameter reads,
stream-interval requests, TIMESYNC), watches the streams for a few seconds and
judges what it saw: one :class:`Check` per line, pass / warn / fail, each with
its reason and, when it is not a pass, the fix.

Two halves: :func:`observe` gathers (the only part that touches the link), and
:func:`judge` decides, a pure function of what was observed and of the run
that is planned, tested against exact answers.
"""

from companion.preflight.judge import judge, summary
from companion.preflight.model import (
    Check,
    CoreCost,
    Observed,
    Plan,
    Status,
)
from companion.preflight.observe import as_data, measure_core, observe
from companion.preflight.rules import params_read

__all__ = [
    "Check",
    "CoreCost",
    "Observed",
    "Plan",
    "Status",
    "as_data",
    "judge",
    "measure_core",
    "observe",
    "params_read",
    "summary",
]
