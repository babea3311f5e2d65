#!/usr/bin/env python3
"""Fly the companion against the SITL while injecting malformed MAVLink.

Usage::

    python scripts/fuzz.py --json --seed 1 --cases 3000 --rate 1000
    python scripts/fuzz.py --json --cases full --rate 2000        # >= 100,000 cases
    python scripts/fuzz.py config --json --seed 1 --n 100         # controller configs

Prints the report (``--json``: one JSON object) and exits 0 when the targets
are met, 1 otherwise. The harness is :mod:`sitl.lab.fuzzing.mavlink` (lab
equipment, kept out of ``companion/``); its docstring describes the topology, the
kinds and the targets. ``config``: the seeded mutation campaign over the controller
config, :mod:`sitl.lab.fuzzing.config`.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

if __name__ == "__main__":
    if sys.argv[1:2] == ["config"]:
        from sitl.lab.fuzzing.config import main as config_main

        sys.exit(config_main(sys.argv[2:]))
    from sitl.lab.fuzzing.mavlink import main

    sys.exit(main())
