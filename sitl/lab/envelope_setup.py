"""What an envelope campaign flies: its cases and the setup they share."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.config import MfcConfig, PidConfig
from companion.profile import VehicleProfile
from sitl.lab.pidtune import TEST_SCENARIOS, apply_params
from sitl.link_model import LinkSpec
from sitl.scenario import Scenario

__all__ = [
    "CASES",
    "CONTROLLERS",
    "ENVELOPE_TEST_SCENARIO",
    "P90_TARGET",
    "RATIO_TARGET",
    "WORST_TARGET",
    "EnvelopeCase",
    "EnvelopeSetup",
    "envelope_cases",
    "load_setup",
    "tuned_config",
]

_ROOT = Path(__file__).resolve().parents[2]
"""The checkout (or install) this module belongs to: bundled profiles are found from it."""

CASES: tuple[str, ...] = ("intact", "motor60", "imbalance", "cg10")
"""Vehicle cases: the intact vehicle and the generator's damage variants."""

CONTROLLERS: tuple[str, ...] = ("mfc", "pid_tuned", "pid_default")
"""The three controllers flown on the test scenario, in record order."""

RATIO_TARGET = 1.25
"""Target: MFC MAE over the tuned PID's MAE, on every vehicle, case and axis."""

WORST_TARGET = 1.1
"""The target for the worst feasible case's worst-axis MFC / tuned PID ratio."""

P90_TARGET = 1.0
"""The target for the 90th percentile of the feasible cases' worst-axis ratio."""

ENVELOPE_TEST_SCENARIO = "envelope-test"
"""The held-out test flight of this campaign (never trained on)."""


@dataclass(frozen=True)
class EnvelopeCase:
    """One vehicle in one condition.

    Attributes
    ----------
    vehicle
        The envelope vehicle's name.
    case
        One of :data:`CASES`.
    profile
        The plant flown (damaged for a damage case).
    info
        The intact vehicle's description (``EnvelopeVehicle.to_dict()``: its
        scalars and derived figures, peak angular accelerations included), so
        a vehicle's cases share one place on the envelope plots.
    """

    vehicle: str
    case: str
    profile: VehicleProfile
    info: dict[str, Any]


@dataclass(frozen=True)
class EnvelopeSetup:
    """What every case of a campaign shares.

    Attributes
    ----------
    mfc
        The MFC configuration, flown unchanged on every vehicle.
    pid_default
        PX4's default PID: the floor, and the tuner's start point.
    controller_profile
        The profile MFC is given (its geometry makes the mixer): the F450's.
    train
        The tuning scenario.
    test
        The test scenario (never tuned on).
    tune_budget
        Flights per tuning run, the start point's included.
    seed
        Seeds every tuning search.
    oracle
        Also fly the oracle on the test scenario (the limit each case is read
        against; the campaign's default). Off, a record's ``oracle`` and
        ``ratio_mfc_oracle`` are None.
    """

    mfc: MfcConfig
    pid_default: PidConfig
    controller_profile: VehicleProfile
    train: Scenario
    test: Scenario
    tune_budget: int = 40
    seed: int = 1
    oracle: bool = True

    def __post_init__(self) -> None:
        held_out = TEST_SCENARIOS | {ENVELOPE_TEST_SCENARIO, self.test.name}
        if self.train.name in held_out:
            raise ValueError(
                f"training scenario {self.train.name!r} is a test flight; "
                f"tune on one that is not in {sorted(held_out)}"
            )
        if self.tune_budget < 1:
            raise ValueError(f"tune_budget must be at least 1 flight, got {self.tune_budget}")


def load_setup(
    *,
    controller: str | Path | None = None,
    controller_profile: str | Path = "vehicle_profiles/f450.yaml",
    train_scenario: str | Path = "train-acro",
    test_scenario: str | Path = ENVELOPE_TEST_SCENARIO,
    tune_budget: int = 40,
    seed: int = 1,
    link: LinkSpec | None = None,
) -> EnvelopeSetup:
    """Load the files of an :class:`EnvelopeSetup` (the PID floor is PX4's defaults).

    Parameters
    ----------
    controller
        MFC file; default the shipped one (:data:`~companion.config.DEFAULT_CONTROLLER`).
    controller_profile
        The profile MFC is given; a relative path missing from the working
        directory is looked up in the repository.
    train_scenario, test_scenario
        Scenario names or files.
    tune_budget, seed
        As in :class:`EnvelopeSetup`.
    link
        The companion link every flight goes through (tuning included: the PID
        is tuned through the same link); default: each scenario's own.

    Raises
    ------
    companion.errors.ConfigError
        A file that does not load.
    ValueError
        A controller that is not MFC, or a setup :class:`EnvelopeSetup` refuses.
    """
    from companion.config import DEFAULT_CONTROLLER, PID_DEFAULT_CONTROLLER, load_controller
    from companion.profile import load_profile
    from sitl.scenario import load_scenario

    prof_path = Path(controller_profile)
    if not prof_path.exists() and not prof_path.is_absolute():
        prof_path = _ROOT / prof_path
    mfc_path = Path(controller) if controller is not None else DEFAULT_CONTROLLER
    mfc = load_controller(mfc_path)
    if not isinstance(mfc, MfcConfig):
        raise ValueError(f"{mfc_path} is a {mfc.kind} file; the envelope campaign flies MFC")
    pid_default = load_controller(PID_DEFAULT_CONTROLLER)
    if not isinstance(pid_default, PidConfig):
        raise ValueError(f"{PID_DEFAULT_CONTROLLER} is not a PID file")
    return EnvelopeSetup(
        mfc=mfc,
        pid_default=pid_default,
        controller_profile=load_profile(prof_path),
        train=_with_link(load_scenario(train_scenario), link),
        test=_with_link(load_scenario(test_scenario), link),
        tune_budget=tune_budget,
        seed=seed,
    )


def _with_link(sc: Scenario, link: LinkSpec | None) -> Scenario:
    return sc if link is None else sc.model_copy(update={"link": link})


def envelope_cases(
    n: int = 30,
    seed: int = 1,
    *,
    corners_only: bool = False,
    damage: bool = True,
    damage_on: int = 8,
) -> list[EnvelopeCase]:
    """The campaign's cases: the corners, ``n`` sampled vehicles, damage on some.

    Parameters
    ----------
    n
        Latin-hypercube vehicles (:func:`sitl.envelope.sample_envelope`).
    seed
        The sample's seed.
    corners_only
        Only the named corner vehicles (:func:`sitl.envelope.corners`).
    damage
        Add the damage variants (``motor60``, ``imbalance``, ``cg10``).
    damage_on
        How many vehicles get them: the first ``damage_on`` of the list, which
        starts with the corners, then the sampled vehicles in sample order.

    Returns
    -------
    list of EnvelopeCase
        Vehicle by vehicle, each vehicle's intact case first.
    """
    from sitl.envelope import corners, damage_variants, sample_envelope

    if n < 0 or damage_on < 0:
        raise ValueError(f"n and damage_on must be >= 0, got {n} and {damage_on}")
    vehicles = list(corners()) + ([] if corners_only else list(sample_envelope(n, seed)))
    names = [v.name for v in vehicles]
    if len(set(names)) != len(names):
        raise ValueError(f"envelope vehicle names are not unique: {names}")
    cases: list[EnvelopeCase] = []
    for i, v in enumerate(vehicles):
        info = dict(v.to_dict())
        cases.append(EnvelopeCase(v.name, "intact", v.profile(), info))
        if damage and i < damage_on:
            variants = damage_variants(v)
            for case in CASES[1:]:
                cases.append(EnvelopeCase(v.name, case, variants[case], info))
    return cases


def tuned_config(setup: EnvelopeSetup, gains: dict[str, float]) -> PidConfig:
    """PX4's default PID with the tuned ``gains`` applied."""
    return apply_params(setup.pid_default, gains)
