"""Child processes that do not outlive the lab process that started them.

:func:`fly_mavlink` and the loop benchmark start the SITL and the companion as
separate processes and stop them in a ``finally``. That covers an exception and
Ctrl-C, not a ``SIGKILL`` (a CI runner's timeout, ``kill -9``, the OOM killer) nor
a ``SIGTERM`` to a process without a handler: the children were left running, a
lockstep SITL spinning a core with nobody to fly it.

:func:`start` asks Linux to send the child ``SIGTERM`` when its parent dies
(``prctl(PR_SET_PDEATHSIG)``), which both programs answer by ending their flight
and writing their logs. Elsewhere (no ``prctl``) it is a plain ``Popen``.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["start"]

_PR_SET_PDEATHSIG = 1


def _tie_to(parent_pid: int) -> Callable[[], None] | None:
    """The ``preexec_fn`` that ties the child to ``parent_pid`` (None off Linux)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None

    def tie() -> None:
        # Runs in the child between fork and exec.
        prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
        if os.getppid() != parent_pid:  # the parent died before the request was made
            os.kill(os.getpid(), signal.SIGTERM)

    return tie


def start(cmd: Sequence[str], **popen_kwargs: Any) -> subprocess.Popen[bytes]:
    """``subprocess.Popen(cmd, **popen_kwargs)``, the child sent ``SIGTERM`` if this
    process dies first (Linux). The signal comes when the *thread* that started the
    child ends, so start children from a thread that outlives them (the callers here
    wait for their children on the same thread)."""
    return subprocess.Popen(list(cmd), preexec_fn=_tie_to(os.getpid()), **popen_kwargs)
