#!/usr/bin/env python3
"""Reproduce the paper's Section IV in simulation: the command line of :mod:`sitl.lab.paper`.

Usage::

    python scripts/reproduce_paper.py --out runs/paper          # full 60 s flights
    python scripts/reproduce_paper.py --out /tmp/paper --quick  # 15 s slices (smoke test)

``--help`` gives the whole description (the package's docstring). Exits 0 when every
flight flew, 1 when one raised, 2 on a bad argument or a scheduler that does not answer.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from sitl.lab import paper
from sitl.lab.paper.flights import QUICK_S


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=paper.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--quick", action="store_true", help=f"fly only the first {QUICK_S:g} s")
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument(
        "--scheduler",
        default=None,
        help="fly on a running Dask cluster at this address (tcp://HOST:8786) "
        "[default: --workers processes on this machine]",
    )
    ap.add_argument(
        "--link",
        default=None,
        help="fly every flight through this companion link (a profile of "
        "sitl/link_model.py such as uart or usb-serial, or fields such as delay_ms=10) "
        "[default: the scenario's, the ideal link]",
    )
    args = ap.parse_args(argv)
    if args.link is not None:
        from sitl.link_model import parse_link

        try:
            parse_link(args.link)
        except ValueError as exc:
            ap.error(f"--link: {exc}")
    if args.workers < 1:
        ap.error(f"--workers: expected 1 or more, got {args.workers}")
    from companion.options import out_dir_problem

    problem = out_dir_problem(args.out)
    if problem is not None:
        ap.error(f"--out: {problem}")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    # Each worker logs its flight's crash; keep the console for the bar and the summary.
    logging.getLogger("sitl").setLevel(logging.WARNING)

    from sitl.lab.paper.run import SchedulerError, run

    try:
        return run(
            Path(args.out), quick=args.quick, workers=args.workers, scheduler=args.scheduler,
            link=args.link, progress=not args.no_progress,
        )  # fmt: skip
    except SchedulerError as exc:
        ap.error(f"--scheduler: {exc}")


if __name__ == "__main__":
    sys.exit(main())
