#!/usr/bin/env python3
"""Fly the companion against the SITL while injecting malformed MAVLink.

Usage::

    python scripts/fuzz.py --json --seed 1 --cases 3000 --rate 1000
    python scripts/fuzz.py --json --cases full --rate 2000        # >= 100,000 cases

Prints the report (``--json``: one JSON object) and exits 0 when the targets
are met, 1 otherwise. The harness is ``tests/fuzzing.py`` (test equipment,
kept out of ``companion/``); its docstring describes the topology, the kinds
and the targets.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.fuzzing import main

if __name__ == "__main__":
    sys.exit(main())
