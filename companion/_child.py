"""A child process's entry (:mod:`companion.child_process`)."""

from __future__ import annotations

import os
import signal
import sys


def main() -> int:
    # A Ctrl-C at the terminal, or a service manager's SIGTERM to the whole group,
    # is the companion's to act on: it finishes its records through this child,
    # then closes its input, and this child ends then (or when the companion dies).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    nice = int(sys.argv[1]) if len(sys.argv) > 1 else 0
    if nice and hasattr(os, "nice"):
        os.nice(nice)
    # Our frames go out on a private copy of stdout; whatever an import prints goes
    # to stderr instead of into them.
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    from companion.child_process import serve

    return serve(sys.stdin.buffer, out)


if __name__ == "__main__":
    sys.exit(main())
