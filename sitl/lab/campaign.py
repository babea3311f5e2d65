"""Campaigns: many in-process flights over a grid, in parallel, summarised.

The grid is profiles x damage severity x wind gust sigma x seeds x controllers.
Every flight runs :func:`sitl.lab.simulate.simulate_flight` (no MAVLink) on a
Dask cluster (:mod:`sitl.lab.executor`: local worker processes, or a running
cluster's); each is deterministic, so the records do not depend on the workers,
where they run or the order flights finish in. Each finished flight is stored
in the output folder as it completes (:mod:`sitl.lab.campaign_store`), so a
killed run resumes where it stopped.

Grid axes
---------
profile
    A vehicle profile (default: every file in ``vehicle_profiles/``).
damage
    Efficiency of motor 1 (index 0, front right): its thrust and reaction-torque
    efficiencies are multiplied by this factor, on top of any damage the profile
    already has (the cut-prop F450's motor 1 is at 0.686 of thrust to begin
    with). 1.0 leaves the profile unchanged.
gust
    The scenario's wind with its gust sigma (m/s) replaced; the steady wind is
    kept.
seed
    Overrides the scenario's seed: with ``train-acro`` (pilot ``acro-random``)
    each seed is a different random acro flight, plus its own wind and noise.
controller
    A controller file, flown unchanged on every vehicle.

Outputs (:func:`write_outputs`): ``flights.parquet`` (one row per flight; the
schema is in :mod:`sitl.lab.table`), and from it ``campaign.json`` (``meta``
and ``records``, one record per flight in grid order: ``profile``, ``damage``,
``gust_sigma_m_s``, ``seed``, ``controller``, ``controller_kind``, ``mae_deg_s``
per axis, ``crashed``, ``crashed_at_s``, ``saturation_any``, ``sim_time_s``,
``feasible``, then ``flight_id``, ``scenario``, ``duration_s``, ``rms_deg_s``
per axis, ``error``, ``wall_time_s`` and ``oracle_mae_deg_s`` per axis: the
oracle's MAE in the flight's case, the limit it is read against), ``summary.md`` (median and 90th
percentile MAE per controller and axis, crash counts on feasible cases and
infeasible flights) and ``mae.png`` (box plots of the per-axis MAE by
controller). A flight that raised is a record with its ``error``, ``crashed``
null and no figures; the campaign goes on.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from companion.config import MfcConfig, PidConfig
from companion.control import AXES
from companion.profile import MotorDamage, VehicleProfile
from sitl.lab.campaign_report import CAMPAIGN_FILES, plot_mae, summary_markdown, write_outputs
from sitl.lab.campaign_spec import FlightSpec
from sitl.scenario import Scenario

if TYPE_CHECKING:
    from sitl.lab.campaign_store import CampaignStore
    from sitl.lab.executor import Executor

__all__ = [
    "CAMPAIGN_FILES",
    "FlightSpec",
    "Grid",
    "build_grid",
    "damaged_profile",
    "fly_one",
    "oracle_crashes",
    "oracle_limit",
    "plot_mae",
    "run_campaign",
    "summary_markdown",
    "write_outputs",
]

_log = logging.getLogger(__name__)


def damaged_profile(profile: VehicleProfile, efficiency: float, motor: int = 0) -> VehicleProfile:
    """``profile`` with one motor's thrust and torque efficiency scaled by ``efficiency``.

    Parameters
    ----------
    profile
        The vehicle; it is not changed (profiles are frozen).
    efficiency
        Factor in (0, 1.5]; 1.0 returns ``profile`` itself.
    motor
        Index of the motor (output order).

    Returns
    -------
    VehicleProfile
        A validated copy; the factor multiplies any damage already on that motor.
    """
    if efficiency == 1.0:
        return profile
    if not 0.0 < efficiency <= 1.5:
        raise ValueError(f"efficiency must be in (0, 1.5], got {efficiency}")
    if not 0 <= motor < profile.n_motors:
        raise ValueError(f"motor index {motor} out of range 0..{profile.n_motors - 1}")
    dmg = profile.physics.damage
    motors = list(dmg.motors)
    for i, m in enumerate(motors):
        if m.motor == motor:
            motors[i] = m.model_copy(
                update={
                    "thrust_efficiency": m.thrust_efficiency * efficiency,
                    "torque_efficiency": m.torque_efficiency * efficiency,
                }
            )
            break
    else:
        motors.append(
            MotorDamage(motor=motor, thrust_efficiency=efficiency, torque_efficiency=efficiency)
        )
    physics = profile.physics.model_copy(
        update={"damage": dmg.model_copy(update={"motors": motors})}
    )
    copy = profile.model_copy(
        update={"physics": physics, "name": f"{profile.name} (motor {motor + 1} at {efficiency:g})"}
    )
    # model_copy does not validate: do it once here, at the edge.
    return VehicleProfile.model_validate(copy.model_dump())


@dataclass(frozen=True)
class Grid:
    """A campaign's grid, expanded lazily: each iteration builds its specs one at a
    time, in a fixed order (profile, damage, gust, seed, controller), and ``len``
    is the product of the axes' lengths. A grid of a million seeds holds its axes,
    not its flights. ``duration_s`` flies only the first seconds of the scenario;
    the specs share their profile, controller and scenario objects."""

    profiles: dict[str, VehicleProfile]
    controllers: dict[str, MfcConfig | PidConfig]
    scenario: Scenario
    damages: Sequence[float] = (1.0, 0.8, 0.6)
    gusts_m_s: Sequence[float] = (0.0, 2.0)
    seeds: Sequence[int] = (1000, 1001, 1002)
    duration_s: float | None = None

    def __iter__(self) -> Iterator[FlightSpec]:
        base = self.scenario
        if self.duration_s is not None:
            base = base.model_copy(update={"duration_s": self.duration_s})
        for pname, prof in self.profiles.items():
            for dmg in self.damages:
                vehicle = damaged_profile(prof, dmg)
                for gust in self.gusts_m_s:
                    # Validated (model_copy is not): a bad gust is a ValueError here,
                    # not a failure inside a worker's flight.
                    wind = type(base.wind).model_validate(
                        {**base.wind.model_dump(), "gust_sigma_m_s": float(gust)}
                    )
                    sc = base.model_copy(update={"wind": wind})
                    for seed in self.seeds:
                        for cname, cfg in self.controllers.items():
                            yield FlightSpec(
                                pname, vehicle, float(dmg), float(gust), int(seed), cname, cfg,
                                sc,
                            )  # fmt: skip

    def __len__(self) -> int:
        return (
            len(self.profiles) * len(self.damages) * len(self.gusts_m_s) * len(self.seeds)
            * len(self.controllers)
        )  # fmt: skip


def build_grid(
    profiles: dict[str, VehicleProfile],
    controllers: dict[str, MfcConfig | PidConfig],
    scenario: Scenario,
    *,
    damages: Sequence[float] = (1.0, 0.8, 0.6),
    gusts_m_s: Sequence[float] = (0.0, 2.0),
    seeds: Sequence[int] = (1000, 1001, 1002),
    duration_s: float | None = None,
) -> list[FlightSpec]:
    """The :class:`Grid`'s specs, all built (a list)."""
    return list(Grid(profiles, controllers, scenario, damages, gusts_m_s, seeds, duration_s))


def _versions() -> dict[str, str]:
    """The versions that shape a flight, on the process that flies it."""
    from sitl.lab.report import versions

    v = versions()
    return {"mfc_companion": v["mfc-companion"], "python": v["python"], "numpy": v["numpy"]}


def _spec_fields(spec: FlightSpec) -> dict[str, Any]:
    return {
        "profile": spec.profile_name,
        "damage": spec.damage,
        "gust_sigma_m_s": spec.gust_sigma_m_s,
        "seed": spec.seed,
        "controller": spec.controller_name,
        "controller_kind": spec.controller.kind,
        "scenario": spec.scenario.name,
        "duration_s": spec.scenario.duration_s,
    }


def fly_one(spec: FlightSpec) -> dict[str, Any]:
    """Fly one spec and return its record (a top-level function, for the workers).

    The record: the spec's fields (:data:`sitl.lab.table.SPEC_COLUMNS`),
    ``mae_deg_s`` and ``rms_deg_s`` per axis, ``crashed``, ``crashed_at_s``,
    ``saturation_any``, ``sim_time_s``, ``error`` (None), ``wall_time_s`` (of
    this flight) and the worker's ``versions``.
    """
    from sitl.lab.report import compute_metrics
    from sitl.lab.simulate import simulate_flight

    t0 = time.perf_counter()
    m = compute_metrics(
        simulate_flight(spec.profile, spec.controller, spec.scenario, seed=spec.seed)
    )
    return {
        **_spec_fields(spec),
        "mae_deg_s": m["mae_deg_s"],
        "rms_deg_s": m["rms_deg_s"],
        "crashed": m["crashed"],
        "crashed_at_s": m["crashed_at_s"],
        "saturation_any": m["saturation_fraction"]["any"],
        "sim_time_s": m["sim_time_s"],
        "error": None,
        "wall_time_s": round(time.perf_counter() - t0, 3),
        "versions": _versions(),
    }


def _failed_record(spec: FlightSpec, error: str) -> dict[str, Any]:
    """The record of a flight that raised (or whose task was lost): no figures."""
    none = {a: None for a in AXES}
    return {
        **_spec_fields(spec),
        "mae_deg_s": none,
        "rms_deg_s": none,
        "crashed": None,
        "crashed_at_s": None,
        "saturation_any": None,
        "sim_time_s": None,
        "error": error,
        "wall_time_s": None,
        "versions": {},
    }


def oracle_crashes(spec: FlightSpec) -> bool:
    """Whether the oracle that may also set the collective (sitl.lab.oracle) crashes
    in ``spec``'s case: if it does, no controller could have flown it (a top-level
    function, for the workers)."""
    from sitl.lab.oracle import oracle_flight

    crashed: bool = oracle_flight(spec.profile, spec.scenario, seed=spec.seed, collective=True)[
        "crashed"
    ]
    return crashed


def oracle_limit(spec: FlightSpec) -> dict[str, Any]:
    """The oracle's flight in ``spec``'s case (:mod:`sitl.lab.oracle`: a law that knows
    the plant and sees its true state, the pilot's collective): its MAE per axis,
    the limit the case's flights are read against (a top-level function, for the
    workers)."""
    from sitl.lab.oracle import oracle_flight

    m = oracle_flight(spec.profile, spec.scenario, seed=spec.seed)
    return {"mae_deg_s": m["mae_deg_s"], "crashed": m["crashed"]}


def _first_unseen(
    specs: Iterable[FlightSpec], keys: Iterable[str], seen: set[str], sent: list[str]
) -> Iterator[FlightSpec]:
    """The first spec of each key not in ``seen``, lazily; each one's key is appended
    to ``sent`` as it is handed out (so an outcome's index names its key)."""
    for spec, key in zip(specs, keys):
        if key not in seen:
            seen.add(key)
            sent.append(key)
            yield spec


def _is_crash(record: dict[str, Any]) -> bool:
    return record.get("crashed") is True


def run_campaign(
    specs: Grid | Sequence[FlightSpec],
    *,
    workers: int | None = 2,
    progress: bool = True,
    scheduler: str | None = None,
    executor: Executor | None = None,
    store: CampaignStore | None = None,
    oracle: bool = True,
) -> list[dict[str, Any]]:
    """Fly every spec on a Dask cluster with a tqdm bar; records in spec order.

    Then, for each case (a vehicle, its damage, the gust and the seed) where any
    controller crashed, the oracle that may also set the collective flies it: each
    record's ``feasible`` is False when that oracle crashes too (the case is beyond
    any controller, reported apart and left out of the crash counts), None when
    its flight raised, True otherwise.

    Parameters
    ----------
    specs
        The grid: a :class:`Grid` (expanded lazily, a few passes over it) or a
        list (:func:`build_grid`). Specs are handed to the workers as they free
        up; only their ids and the records are kept.
    workers, scheduler
        The cluster when ``executor`` is None (:class:`sitl.lab.executor.Executor`):
        ``workers`` local processes (at most one per flight; None: one per core),
        or the running cluster at ``scheduler``.
    executor
        An open executor to run on (its cluster is reused, not closed).
    progress
        Show the bars (flights, then oracle cases).
    store
        Where each flight's record and each case's verdict is written as it
        completes; those already there are not flown again. None keeps them in
        memory only.
    oracle
        Also fly the oracle once per case (:func:`oracle_limit`): each record's
        ``oracle_mae_deg_s`` is its MAE per axis (None when not flown or when
        its flight raised).

    Returns
    -------
    list of dict
        :func:`fly_one`'s records (or a failed flight's), each with its
        ``flight_id`` and ``feasible``.
    """
    from sitl.lab.campaign_store import case_ids, flight_ids
    from sitl.lab.executor import Executor, TaskOutcome

    if executor is None:
        n = min(workers or os.cpu_count() or 1, max(1, len(specs)))
        with Executor(scheduler, n) as ex:
            return run_campaign(specs, progress=progress, executor=ex, store=store, oracle=oracle)
    ids = flight_ids(specs)
    flown: dict[str, dict[str, Any]] = store.flights(ids) if store else {}
    sent: list[str] = []  # the flight id of each spec handed out, in order

    def keep_flight(o: TaskOutcome) -> None:
        fid = sent[o.index]
        rec = o.value if o.ok else _failed_record(o.item, str(o.error))
        rec = {**rec, "flight_id": fid}
        if store:
            store.save_flight(fid, rec)
        flown[fid] = rec

    n_todo = len(set(ids) - set(flown))
    if n_todo:
        executor.run(
            fly_one, _first_unseen(specs, ids, set(flown), sent), on_result=keep_flight,
            total=n_todo, collect=False,
            tally=lambda r: "crashed" if _is_crash(r) else None,
            desc="campaign", unit="flight", progress=progress,
        )  # fmt: skip
    cids = case_ids(specs)
    crashed: dict[str, FlightSpec] = {}
    for spec, fid, cid in zip(specs, ids, cids):
        if _is_crash(flown[fid]):
            crashed.setdefault(cid, spec)
    judged: dict[str, dict[str, Any]] = store.verdicts(crashed) if store else {}
    to_judge = [cid for cid in crashed if cid not in judged]

    def keep_verdict(o: TaskOutcome) -> None:
        cid = to_judge[o.index]
        verdict = {"case_id": cid, "oracle_crashed": o.value, "error": o.error}
        if store:
            store.save_verdict(cid, verdict)
        judged[cid] = verdict

    if to_judge:
        executor.run(
            oracle_crashes, (crashed[c] for c in to_judge), on_result=keep_verdict,
            total=len(to_judge), tally=lambda bad: "infeasible" if bad else None,
            desc="oracle", unit="case", progress=progress,
        )  # fmt: skip
    limits = _limits(specs, cids, executor, store, progress) if oracle else {}
    records = []
    for fid, cid in zip(ids, cids):
        v = judged.get(cid)
        feasible = True if v is None else None if v["error"] else not v["oracle_crashed"]
        lim = limits.get(cid)
        mae = lim["mae_deg_s"] if lim and not lim.get("error") else None
        records.append({**flown[fid], "feasible": feasible, "oracle_mae_deg_s": mae})
    return records


def _limits(
    specs: Grid | Sequence[FlightSpec],
    cids: Sequence[str],
    executor: Executor,
    store: CampaignStore | None,
    progress: bool,
) -> dict[str, dict[str, Any]]:
    """The oracle's flight in every case, by case id (stored as each completes; the
    grid is walked lazily, the first spec of each case flown)."""
    from sitl.lab.executor import TaskOutcome

    limits: dict[str, dict[str, Any]] = store.limits(dict.fromkeys(cids)) if store else {}
    sent: list[str] = []  # the case id of each spec handed out, in order

    def keep(o: TaskOutcome) -> None:
        cid = sent[o.index]
        limit = {"case_id": cid, **(o.value or {}), "error": o.error}
        if store:
            store.save_limit(cid, limit)
        limits[cid] = limit

    n_todo = len(set(cids) - set(limits))
    if n_todo:
        executor.run(
            oracle_limit, _first_unseen(specs, cids, set(limits), sent), on_result=keep,
            total=n_todo, collect=False,
            desc="oracle limit", unit="case", progress=progress,
        )  # fmt: skip
    return limits
