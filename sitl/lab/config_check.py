"""A controller config flown before it flies: ``companion check-config --fly``.

The schema takes each value within its range; a combination can still be
unstable. So a config is flown, in process, on reference vehicles (the paper's
three and two corners of the envelope: the highest and the lowest angular
acceleration), on the ``config-check`` scenario (10 s of seeded all-axis acro,
wind and gusts), with the shipped controller flown beside it on the same
flights. It fails when any flight crashes, or when on any vehicle and axis its
mean absolute tracking error exceeds the shipped controller's by more than
:data:`EXCESS_MAX_DEG_S`.

The controller is given the F450's profile on every vehicle, as the envelope
campaign gives it (one config, vehicles it was not told about), and flies
actuator output (the bundled plant's motors); the rates output's plant is the
autopilot's own rate loop, which only the MAVLink SITL has.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.config import DEFAULT_CONTROLLER, MfcConfig, PidConfig, load_controller
from companion.control import AXES
from companion.profile import VehicleProfile, load_profile

if TYPE_CHECKING:
    from sitl.scenario import Scenario

__all__ = [
    "CHECK_SCENARIO",
    "EXCESS_MAX_DEG_S",
    "CheckFlight",
    "check_controller",
    "fly_flight",
    "judge_flight",
    "reference_vehicles",
]

CHECK_SCENARIO = "config-check"

EXCESS_MAX_DEG_S = 20.0
"""Mean absolute error allowed beyond the shipped controller's, per vehicle and
axis (deg/s): beyond it a config counts as blowing up."""

_ROOT = Path(__file__).resolve().parents[2]
_PROFILES = _ROOT / "vehicle_profiles"
_PAPER_VEHICLES = ("f450", "f450_cut_props", "tarot650")
_CORNERS = ("tiny-fast", "heavy-weak")


def reference_vehicles() -> list[VehicleProfile]:
    """The paper's three vehicles, then the envelope's fastest and slowest corners."""
    from sitl.envelope import corners

    paper = [load_profile(_PROFILES / f"{name}.yaml", simulated=True) for name in _PAPER_VEHICLES]
    corner = [v.profile() for v in corners() if v.name in _CORNERS]
    return paper + corner


@dataclass(frozen=True)
class CheckFlight:
    """One vehicle flown by the config and by the shipped controller."""

    vehicle: str
    crashed: bool
    mae_deg_s: dict[str, float | None]
    shipped_mae_deg_s: dict[str, float | None]
    problems: tuple[str, ...]

    @property
    def passed(self) -> bool:
        return not self.problems

    def as_dict(self) -> dict[str, Any]:
        return {
            "vehicle": self.vehicle,
            "passed": self.passed,
            "crashed": self.crashed,
            "mae_deg_s": self.mae_deg_s,
            "shipped_mae_deg_s": self.shipped_mae_deg_s,
            "problems": list(self.problems),
        }


def fly_flight(
    plant: VehicleProfile,
    cfg: MfcConfig | PidConfig,
    given: VehicleProfile,
    scenario: Scenario | None = None,
) -> dict[str, Any]:
    """One flight of ``cfg`` given ``given``'s profile on ``plant``: ``crashed`` and
    ``mae_deg_s`` per axis (the check's scenario unless another is given)."""
    from sitl.lab.report import compute_metrics
    from sitl.lab.simulate import simulate_flight
    from sitl.scenario import load_scenario

    sc = load_scenario(CHECK_SCENARIO) if scenario is None else scenario
    m = compute_metrics(simulate_flight(plant, cfg, sc, controller_profile=given))
    return {"crashed": bool(m["crashed"]), "mae_deg_s": m["mae_deg_s"]}


def _fly(args: tuple[VehicleProfile, MfcConfig | PidConfig, VehicleProfile]) -> dict[str, Any]:
    return fly_flight(*args)


def judge_flight(vehicle: str, flown: dict[str, Any], shipped: dict[str, Any]) -> CheckFlight:
    """A flight of the config against the shipped controller's same flight."""
    problems = []
    if flown["crashed"]:
        problems.append(f"{vehicle}: crashed")
    for a in AXES:
        got, ref = flown["mae_deg_s"][a], shipped["mae_deg_s"][a]
        if got is None or ref is None:
            continue  # never airborne: a crash, said above, or the shipped one's too
        if got > ref + EXCESS_MAX_DEG_S:
            problems.append(
                f"{vehicle}: {a} error {got:.1f} deg/s, beyond the shipped controller's "
                f"{ref:.1f} + {EXCESS_MAX_DEG_S:g}"
            )
    return CheckFlight(
        vehicle, flown["crashed"], flown["mae_deg_s"], shipped["mae_deg_s"], tuple(problems)
    )


_SHIPPED: dict[str, dict[str, Any]] = {}
"""The shipped controller's flights, by vehicle name (deterministic: flown once
per process)."""


def check_controller(
    cfg: MfcConfig | PidConfig,
    *,
    vehicles: list[VehicleProfile] | None = None,
    workers: int = 1,
) -> list[CheckFlight]:
    """Fly ``cfg`` and the shipped controller on each reference vehicle.

    Deterministic: the scenario is seeded, and the flights do not depend on
    ``workers`` (processes, one flight each).
    """
    vehicles = reference_vehicles() if vehicles is None else vehicles
    given = load_profile(_PROFILES / "f450.yaml")
    shipped = load_controller(DEFAULT_CONTROLLER)
    todo = [v for v in vehicles if v.name not in _SHIPPED]
    jobs = [(v, cfg, given) for v in vehicles] + [(v, shipped, given) for v in todo]
    if workers <= 1:
        results = [_fly(j) for j in jobs]
    else:
        with ProcessPoolExecutor(workers) as pool:
            results = list(pool.map(_fly, jobs))
    flown = results[: len(vehicles)]
    _SHIPPED.update({v.name: r for v, r in zip(todo, results[len(vehicles) :], strict=True)})
    return [judge_flight(v.name, r, _SHIPPED[v.name]) for v, r in zip(vehicles, flown, strict=True)]
