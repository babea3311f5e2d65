"""The shipped controller through companion links, against the round trip's own cost.

A command computed from a sample moves the motors one round trip later, so even
a controller that knows the plant and predicts it perfectly answers each stick
move that late. Through a link, MFC's roll and pitch are judged against that
limit: the ideal tracker's MAE one round trip late
(:func:`sitl.lab.paper.analysis.ideal_tracker_through_link_deg_s`, the link's
own seeded draws), as a ratio to the same ratio on the ideal link::

    cost = (MFC_link / tracker_link) / (MFC_ideal / tracker_ideal)

A cost of 1 means the link took from MFC only what it takes from a perfect
tracker. Each flight is the full ``paper-acro`` through the product's flight
core (:func:`sitl.lab.simulate.simulate_flight`), actuator output, PX4's
allocation in the plant's autopilot. Yaw has no ideal tracker (a rotor's
spin-up reaction gives it far more than its steady peak for a moment); its
figure is the ratio to the ideal link's.

With ``--output rates`` each flight is the companion sending body rates
(``mfc_rates.yaml``) to the SITL's PX4 rate loop, over MAVLink in lockstep
(:func:`sitl.lab.fly.fly_mavlink`, the SITL modelling the link): the
autopilot's rate loop is in the plant, the tracker the same. With
``--passthrough`` as well, the companion passes the pilot's rates through
(``companion run --rates-passthrough``): what the autopilot's own rate loop
makes of the same flights and links, judged the same way. ``--sitl-param
NAME=VALUE`` (rates only, repeatable) sets a parameter of the SITL's PX4 at
boot (``sitl run --param``), e.g. its rate loop's gain ``MC_ROLLRATE_K``.
``--law-axes AXES`` (rates only) has the law correct only those axes
(``companion run --rates-law-axes``). ``--link SPEC`` (repeatable) flies
through those links instead of UART, USB-serial and 10 ms each way, named or
as fields (``sitl run --link``: ``delay_ms=5``); the ideal link is always
flown, and a link without a target is given its cost and no verdict.

Run::

    python -m sitl.lab.link_limit [--out DIR] [--workers N] [--duration S] [--seeds N]
                                  [--output actuator|rates] [--passthrough]
                                  [--sitl-param NAME=VALUE ...] [--law-axes AXES]
                                  [--link SPEC ...]

prints a Markdown table (with ``--seeds``, each cost the mean of the seeds')
and writes ``link_limit.json`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from companion.control import AXES

__all__ = ["LINKS", "TARGETS", "VEHICLES", "cost_table", "fly_through"]

ROOT = Path(__file__).resolve().parents[2]
VEHICLES = ("f450", "f450_cut_props", "tarot650", "x500")
LINKS = ("ideal", "uart", "usb-serial", "delay_ms=10")
RATES_CONTROLLER = ROOT / "companion" / "data" / "mfc_rates.yaml"
TARGETS = {"uart": 1.1, "usb-serial": 1.1, "delay_ms=10": 1.25}
"""The most a link may cost MFC beyond what it costs the ideal tracker, roll and pitch."""


def fly_through(
    job: tuple[str, str, float | None, int | None],
    output: str = "actuator",
    passthrough: bool = False,
    sitl_params: tuple[str, ...] = (),
    law_axes: str | None = None,
) -> dict[str, Any]:
    """One paper flight of ``vehicle`` through ``link`` (on ``seed``, default the
    scenario's): MFC's MAE per axis and the ideal tracker's (ideal link: as the
    gyro reports it; a link: one round trip late), deg/s; whether it crashed, and
    the failsafes that ended it early (the MAE then covers the flight up to them).
    ``output`` ``rates``: over MAVLink to the SITL's rate loop (module docstring);
    ``passthrough`` (rates only): the pilot's rates passed through instead of
    MFC's, their MAE under the same key; ``sitl_params`` (rates only): the
    SITL's ``--param NAME=VALUE`` at boot; ``law_axes`` (rates only): the
    companion's ``--rates-law-axes``."""
    from companion.config import load_controller
    from companion.errors import EXIT_FAILSAFE, EXIT_OK
    from companion.profile import load_profile
    from sitl.lab.paper.analysis import motion_limits
    from sitl.lab.paper.flights import SCENARIO, paper_scenario
    from sitl.lab.report import compute_metrics
    from sitl.lab.simulate import simulate_flight

    vehicle, link, duration_s, seed = job
    if (passthrough or sitl_params or law_axes) and output != "rates":
        what = "passthrough" if passthrough else "sitl_params" if sitl_params else "law_axes"
        raise ValueError(f"{what}: needs output 'rates' (got {output!r})")
    path = ROOT / "vehicle_profiles" / f"{vehicle}.yaml"
    profile = load_profile(path)
    sc = paper_scenario(duration_s, None if link == "ideal" else link)
    if seed is not None:
        sc = sc.model_copy(update={"seed": seed})
    if output == "rates":
        import tempfile

        from sitl.lab.fly import fly_mavlink, merge_logs

        with tempfile.TemporaryDirectory(prefix="link-limit-") as tmp:
            flight = fly_mavlink(
                path, SCENARIO, tmp, controller_path=RATES_CONTROLLER, output="rates",
                duration_s=duration_s, seed=sc.seed, link=sc.link,
                companion_args=[
                    *(["--rates-passthrough"] if passthrough else []),
                    *(["--rates-law-axes", law_axes] if law_axes else []),
                ],
                sitl_args=[a for p in sitl_params for a in ("--param", p)],
            )  # fmt: skip
            if flight.companion_rc not in (EXIT_OK, EXIT_FAILSAFE):
                raise RuntimeError(f"{vehicle} through {link}: {flight.why()}")
            record = merge_logs(flight)
        failsafes = [f"{e['kind']}: {e['detail']}" for e in record.meta["failsafe_events"]]
    else:
        record = simulate_flight(profile, load_controller(), sc)
        failsafes = list(record.meta.get("failsafes", []))
    metrics = compute_metrics(record)
    weight = sc.imu_model(profile).first_stage_filter_weight
    limits = motion_limits(record, profile, weight, sc.link, sc.seed)
    key = "ideal_tracker_measured_deg_s" if link == "ideal" else "ideal_tracker_link_deg_s"
    return {
        "vehicle": vehicle,
        "link": link,
        "seed": sc.seed,
        "controller": "passthrough" if passthrough else "mfc",
        "sitl_params": list(sitl_params),
        "law_axes": record.meta.get("rates_law_axes") or law_axes or "auto",
        "crashed": bool(metrics["crashed"]),
        "failsafes": failsafes,
        "mfc_deg_s": {a: round(float(metrics["mae_deg_s"][a]), 3) for a in AXES},
        "tracker_deg_s": limits[key],
    }


def cost_table(flights: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per vehicle and link other than the ideal: the cost beyond the tracker's on
    roll and pitch (each seed's flight against the ideal link's on the same seed,
    then the mean over the seeds), the yaw's ratio to the ideal link (likewise),
    and the verdict on the mean; any crash, or a failsafe that ended a flight
    early, fails it. A link with no target in :data:`TARGETS` gets no verdict
    (``met`` None)."""
    by = {(f["vehicle"], f["link"], int(f.get("seed", 0))): f for f in flights}
    pairs = sorted({(v, link) for v, link, _ in by if link != "ideal"})
    rows = []
    for vehicle, link in pairs:
        seeds = sorted(s for v, k, s in by if (v, k) == (vehicle, link))
        costs: dict[str, list[float]] = {a: [] for a in AXES[:2]}
        yaw: list[float] = []
        crashed = False
        failsafes: list[str] = []
        for seed in seeds:
            f, base = by[(vehicle, link, seed)], by[(vehicle, "ideal", seed)]
            crashed = crashed or f["crashed"] or base["crashed"]
            failsafes += [*f.get("failsafes", ()), *base.get("failsafes", ())]
            for a in AXES[:2]:
                costs[a].append(
                    (f["mfc_deg_s"][a] / f["tracker_deg_s"][a])
                    / (base["mfc_deg_s"][a] / base["tracker_deg_s"][a])
                )
            yaw.append(f["mfc_deg_s"]["yaw"] / base["mfc_deg_s"]["yaw"])
        cost = {a: round(sum(v) / len(v), 3) for a, v in costs.items()}
        target = TARGETS.get(link)
        rows.append(
            {
                "vehicle": vehicle,
                "link": link,
                "seeds": seeds,
                "cost": cost,
                "cost_per_seed": {a: [round(x, 3) for x in v] for a, v in costs.items()},
                "yaw_ratio": round(sum(yaw) / len(yaw), 3),
                "target": target,
                "crashed": crashed,
                "failsafes": failsafes,
                "met": None
                if target is None
                else not crashed and not failsafes and max(cost.values()) <= target,
            }
        )
    return rows


def _mean(flights: list[dict[str, Any]], key: str, axis: str) -> float:
    return float(sum(f[key][axis] for f in flights)) / len(flights)


def _markdown(flights: list[dict[str, Any]], rows: list[dict[str, Any]]) -> str:
    """The table; MAE columns the mean over the seeds."""
    flown = "pass-through" if any(f.get("controller") == "passthrough" for f in flights) else "MFC"
    axes = flights[0].get("law_axes", "auto")
    if flown == "MFC" and axes not in ("auto", ",".join(AXES)):
        flown = f"MFC (law on {axes})"
    lines = [
        f"| vehicle | link | {flown} roll / pitch / yaw | tracker roll / pitch "
        "| cost roll / pitch | per seed (roll; pitch) | target | yaw / ideal link's | met |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def maes(vehicle: str, link: str) -> str:
        fs = [f for f in flights if (f["vehicle"], f["link"]) == (vehicle, link)]
        m = [_mean(fs, "mfc_deg_s", a) for a in AXES]
        t = [_mean(fs, "tracker_deg_s", a) for a in AXES[:2]]
        ended = sum(bool(f.get("failsafes")) for f in fs)
        crash = " (crashed)" if any(f["crashed"] for f in fs) else ""
        crash += f" (failsafe in {ended} of {len(fs)})" if ended else ""
        return f"{m[0]:.2f} / {m[1]:.2f} / {m[2]:.2f}{crash} | {t[0]:.2f} / {t[1]:.2f}"

    for vehicle in VEHICLES:
        if any(f["vehicle"] == vehicle and f["link"] == "ideal" for f in flights):
            lines.append(f"| {vehicle} | ideal | {maes(vehicle, 'ideal')} | 1 | | | 1 | |")
        for r in rows:
            if r["vehicle"] != vehicle:
                continue
            c, per = r["cost"], r["cost_per_seed"]
            seeds = "; ".join(" ".join(f"{x:.2f}" for x in per[a]) for a in AXES[:2])
            target = "-" if r["target"] is None else r["target"]
            met = "" if r["met"] is None else "yes" if r["met"] else "**no**"
            lines.append(
                f"| {vehicle} | {r['link']} | {maes(vehicle, r['link'])} "
                f"| {c['roll']:.2f} / {c['pitch']:.2f} | {seeds} | {target} "
                f"| {r['yaw_ratio']:.2f} | {met} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sitl.lab.link_limit", description=__doc__)
    ap.add_argument("--out", type=Path, help="write link_limit.json here")
    ap.add_argument("--workers", type=int, default=2, help="flights at once (default 2)")
    ap.add_argument("--duration", type=float, help="seconds of paper-acro (default: all 60 s)")
    ap.add_argument(
        "--vehicle", action="append", choices=VEHICLES, help="fly only these (repeatable)"
    )
    ap.add_argument(
        "--seeds",
        type=int,
        default=1,
        help="fly each on this many seeds, the scenario's and the next ones (default 1)",
    )
    ap.add_argument(
        "--output",
        choices=("actuator", "rates"),
        default="actuator",
        help="actuator: the flight core in process (default); rates: mfc_rates.yaml to the "
        "SITL's rate loop over MAVLink",
    )
    ap.add_argument(
        "--passthrough",
        action="store_true",
        help="with --output rates: pass the pilot's rates through instead of flying MFC "
        "(the autopilot's own rate loop on the same flights)",
    )
    ap.add_argument(
        "--sitl-param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="with --output rates: a parameter of the SITL's PX4 at boot (repeatable), "
        "e.g. MC_ROLLRATE_K=2",
    )
    ap.add_argument(
        "--law-axes",
        metavar="AXES",
        help="with --output rates: the axes the law corrects (companion run --rates-law-axes; "
        "default auto)",
    )
    ap.add_argument(
        "--link",
        action="append",
        default=[],
        metavar="SPEC",
        help="fly through this link instead of uart, usb-serial and delay_ms=10 "
        "(repeatable; a name or fields, as sitl run --link: delay_ms=5,jitter_ms=2); the "
        "ideal link is always flown; a link with no target gets its cost and no verdict",
    )
    args = ap.parse_args(argv)
    from sitl.link_model import parse_link

    for spec in args.link:
        try:
            parse_link(spec)
        except ValueError as e:
            ap.error(f"--link: {e}")
    links = ["ideal", *dict.fromkeys(x for x in args.link if x != "ideal")] if args.link else LINKS
    for flag, given in (
        ("--passthrough", args.passthrough),
        ("--sitl-param", args.sitl_param),
        ("--law-axes", args.law_axes),
    ):
        if given and args.output != "rates":
            ap.error(f"{flag}: needs --output rates (got --output {args.output})")
    if args.workers < 1:
        ap.error(f"--workers: expected at least 1, got {args.workers}")
    if args.seeds < 1:
        ap.error(f"--seeds: expected at least 1, got {args.seeds}")
    from sitl.lab.paper.flights import paper_scenario

    first = paper_scenario(None, None).seed
    vehicles = args.vehicle or list(VEHICLES)
    jobs = [
        (v, link, args.duration, first + k)
        for k in range(args.seeds)
        for v in vehicles
        for link in links
    ]
    with ProcessPoolExecutor(args.workers) as pool:
        n = len(jobs)
        params = tuple(args.sitl_param)
        flights = list(
            pool.map(
                fly_through,
                jobs,
                [args.output] * n,
                [args.passthrough] * n,
                [params] * n,
                [args.law_axes] * n,
            )
        )
    rows = cost_table(flights)
    print(_markdown(flights, rows))
    judged = [r for r in rows if r["met"] is not None]
    if judged:
        met = sum(bool(r["met"]) for r in judged)
        print(f"\n{met} of {len(judged)} vehicle-link pairs within target")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "link_limit.json").write_text(
            json.dumps(
                {
                    "output": args.output,
                    "controller": "passthrough" if args.passthrough else "mfc",
                    "sitl_params": args.sitl_param,
                    "law_axes": args.law_axes or "auto",
                    "flights": flights,
                    "costs": rows,
                },
                indent=2,
            )
            + "\n",
            encoding="utf-8",
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
