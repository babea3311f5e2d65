"""``companion replay``: re-run a controller offline on a recorded control log."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from companion.errors import ConfigError
from companion.options import EXIT_BAD_INPUT, fail_config, keep_earlier, usable_out_file

__all__ = ["REPLAY_TOLERANCE", "replay_cmd"]


REPLAY_TOLERANCE = 1e-6
"""Outputs are of order 1 to 500 (us for u); the recorded controller reproduces
its flight far closer than this (exactly, on the same machine). Enforced only
when replaying as recorded: no --controller or --profile, and a log that names
its controller file."""


@click.command("replay")
@click.argument("log", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--controller",
    "controller_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Controller to re-run [default: the one named in the log, else the shipped default].",
)
@click.option(
    "--profile",
    "profile_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Profile whose geometry makes the mixer [default: the one named in the log].",
)
@click.option(
    "--out",
    "out_path",
    type=click.Path(dir_okay=False),
    callback=usable_out_file,
    default=None,
    help="Write the replayed outputs here as a control log, MCAP (an earlier file of that name "
    "is moved into earlier-<UTC time>/ beside it first).",
)
def replay_cmd(
    log: Path, controller_path: Path | None, profile_path: Path | None, out_path: Path | None
) -> None:
    """Re-run a controller offline on a recorded control log (control.mcap).

    With the recorded controller the outputs must match the log (a check that
    the flight was what the code says); with another controller they show what
    it would have commanded on the same samples (open loop).
    """
    from companion.config import DEFAULT_CONTROLLER, load_controller
    from companion.profile import load_profile
    from companion.records import ControlLog, read_control_log
    from companion.replay import compare, replay

    try:
        cols, meta = read_control_log(log)
    except ValueError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(EXIT_BAD_INPUT)
    ctrl = controller_path or Path(meta.get("controller_path") or DEFAULT_CONTROLLER)
    prof = profile_path or (Path(meta["profile_path"]) if meta.get("profile_path") else None)
    if prof is None:
        click.echo(f"error: {log}: no profile_path in the log; give --profile", err=True)
        sys.exit(EXIT_BAD_INPUT)
    try:
        cfg = load_controller(ctrl)
        profile = load_profile(prof)
    except ConfigError as exc:
        fail_config(exc)
    out = replay(cols, cfg, profile, meta=meta)
    diffs = compare(cols, out)
    engaged = int((cols["engaged"] > 0.5).sum())
    click.echo(f"replayed {engaged} engaged samples of {log} with {ctrl} on {prof}")
    if meta.get("cut_short") == "true":
        click.echo(
            f"note: {log} was not closed by its writer (killed?): read up to its last whole chunk",
            err=True,
        )
    worst = max(diffs.values()) if diffs else 0.0
    for name, d in sorted(diffs.items(), key=lambda kv: -kv[1])[:8]:
        click.echo(f"  {name:24s} max |recorded - replayed| = {d:.3g}")
    click.echo(f"largest difference: {worst:.3g}")
    if out_path is not None:
        keep_earlier(f"--out {out_path}", out_path.parent, (out_path.name,))
        names = list(out)
        with ControlLog(
            out_path, names, meta={"replay_of": str(log), "controller": str(ctrl)}
        ) as w:
            for row in zip(*(out[n].tolist() for n in names), strict=True):
                w.append(row)
        click.echo(f"wrote {out_path}")
    as_recorded = (
        controller_path is None and profile_path is None and bool(meta.get("controller_path"))
    )
    if as_recorded and worst > REPLAY_TOLERANCE:
        # The recorded controller and profile must reproduce their own flight: the
        # laws are deterministic, so a difference means something changed since.
        click.echo(
            f"error: the recorded controller {ctrl} on {prof} does not reproduce {log} "
            f"(largest difference {worst:.3g} > {REPLAY_TOLERANCE:g}): one of the two files "
            "or the code has changed since the flight, or the log was written on another "
            "kind of machine (its floating-point library may round differently)",
            err=True,
        )
        sys.exit(1)
