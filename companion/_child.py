"""A child process's entry (:mod:`companion.child_process`)."""

from __future__ import annotations

import os
import sys


def main() -> int:
    # Our frames go out on a private copy of stdout; whatever an import prints goes
    # to stderr instead of into them.
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    from companion.child_process import serve

    return serve(sys.stdin.buffer, out)


if __name__ == "__main__":
    sys.exit(main())
