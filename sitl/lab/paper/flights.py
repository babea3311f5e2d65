"""The flights of the paper reproduction: which vehicle flies which controller,
on which scenario, each flight's key (for resuming), and flying one of them.

Every flight is ``paper-acro`` (the frozen test flight), flown in process
(:func:`sitl.lab.simulate.simulate_flight`, no MAVLink), with the shipped
controller files loaded as they are; ``"oracle"`` flies :mod:`sitl.lab.oracle`.
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[3]
PROFILE_DIR = ROOT / "vehicle_profiles"
DATA_DIR = Path(str(files("companion") / "data"))
SCENARIO = "paper-acro"
QUICK_S = 15.0

CONTROLLERS = {
    "mfc": "mfc_default.yaml",
    "pid_tuned": "pid_tarot_tuned.yaml",
    "pid_px4": "pid_px4_default.yaml",
    "pid_f450_tuned": "pid_f450_tuned.yaml",
    "pid_cut_tuned": "pid_f450_cut_props_tuned.yaml",
}
"""The controller files flown (in ``companion/data``); ``"oracle"`` is flown too, from
:mod:`sitl.lab.oracle`, with no file."""
CONTROLLER_LABEL = {
    "mfc": "MFC (shipped set)",
    "pid_tuned": "PID tuned on Tarot",
    "pid_px4": "PID, PX4 defaults",
    "pid_f450_tuned": "PID tuned on F450",
    "pid_cut_tuned": "PID tuned on cut props",
    "oracle": "oracle (knows the plant)",
}
PAPER_VEHICLES = ("f450", "f450_cut_props", "tarot650")
OWN_PID = {"f450": "pid_f450_tuned", "f450_cut_props": "pid_cut_tuned", "tarot650": "pid_tuned"}
"""Per paper vehicle, the PID tuned on it (``sitl/lab/pidtune.py`` on ``train-acro``)."""


@dataclass(frozen=True)
class Flight:
    """One flight of the reproduction."""

    name: str
    profile: str
    controller: str
    role: str  # "paper" (a flight of Section IV) or "context"
    section: str
    paper_says: str


FLIGHTS = (
    Flight("f450_mfc", "f450", "mfc", "paper", "IV-A", "MAE < 10 deg/s on every axis"),
    Flight(
        "f450_cut_props_mfc", "f450_cut_props", "mfc", "paper", "IV-B",
        "MAE < 20 deg/s on every axis",
    ),
    Flight(
        "tarot650_mfc", "tarot650", "mfc", "paper", "IV-C",
        "responds well (no figure given)",
    ),
    Flight(
        "tarot650_pid_tuned", "tarot650", "pid_tuned", "paper", "IV-D",
        "a successful flight (no figure given)",
    ),
    Flight(
        "f450_pid_tuned", "f450", "pid_tuned", "paper", "IV-D",
        "degrades; MFC much more robust (no figure given)",
    ),
    Flight("f450_pid_px4", "f450", "pid_px4", "context", "-", "-"),
    Flight("f450_cut_props_pid_px4", "f450_cut_props", "pid_px4", "context", "-", "-"),
    Flight("tarot650_pid_px4", "tarot650", "pid_px4", "context", "-", "-"),
    Flight("f450_cut_props_pid_tuned", "f450_cut_props", "pid_tuned", "context", "-", "-"),
    Flight("f450_pid_f450_tuned", "f450", "pid_f450_tuned", "scoreboard", "-", "-"),
    Flight(
        "f450_cut_props_pid_cut_tuned", "f450_cut_props", "pid_cut_tuned", "scoreboard", "-", "-",
    ),
    Flight("f450_oracle", "f450", "oracle", "scoreboard", "-", "-"),
    Flight("f450_cut_props_oracle", "f450_cut_props", "oracle", "scoreboard", "-", "-"),
    Flight("tarot650_oracle", "tarot650", "oracle", "scoreboard", "-", "-"),
)  # fmt: skip


def sha256_file(path: Path) -> str:
    """The file's sha256, in hex."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def paper_scenario(duration_s: float | None, link_text: str | None) -> Any:
    """``paper-acro``, cut to ``duration_s`` and through the named link when given."""
    from sitl.link_model import parse_link
    from sitl.scenario import load_scenario

    sc = load_scenario(SCENARIO)
    if duration_s is not None:
        sc = sc.model_copy(update={"duration_s": duration_s})
    if link_text is not None:
        sc = sc.model_copy(update={"link": parse_link(link_text)})
    return sc


RUN_MANIFEST = "paper-run.json"
"""The manifest of a run in ``--out`` (its flights' digest), for resuming."""
RECORDS_DIR = "records"
"""Where each flight's metrics are stored as it lands."""


def flight_keys(duration_s: float | None, link_text: str | None) -> list[str]:
    """Each flight's key, in :data:`FLIGHTS` order: a digest of the flight, its
    profile's and controller's file contents, the scenario and the link."""
    from sitl.lab.campaign_store import _digest

    scenario = _digest(paper_scenario(duration_s, link_text).model_dump(mode="json"))
    keys = []
    for f in FLIGHTS:
        ctrl = (
            "oracle"
            if f.controller == "oracle"
            else sha256_file(DATA_DIR / CONTROLLERS[f.controller])
        )
        keys.append(
            _digest(
                {
                    "flight": dataclasses.asdict(f),
                    "profile": sha256_file(PROFILE_DIR / f"{f.profile}.yaml"),
                    "controller": ctrl,
                    "scenario": scenario,
                }
            )[:20]
        )
    return keys


def fly_flight(job: tuple[Flight, float | None, str, str | None]) -> dict[str, Any]:
    """Fly one flight, write its report folder, return its metrics (runs in a worker)."""
    from companion.config import load_controller
    from companion.profile import load_profile
    from sitl.lab.paper.analysis import motion_limits, transient_split
    from sitl.lab.report import write_report
    from sitl.lab.simulate import simulate_flight

    flight, duration_s, out, link_text = job
    profile_path = PROFILE_DIR / f"{flight.profile}.yaml"
    sc = paper_scenario(duration_s, link_text)
    profile = load_profile(profile_path)
    if flight.controller == "oracle":
        from sitl.lab.oracle import fly_oracle

        record = fly_oracle(profile, sc)
        shown = "oracle (sitl/lab/oracle.py)"
    else:
        ctrl_path = DATA_DIR / CONTROLLERS[flight.controller]
        record = simulate_flight(profile, load_controller(ctrl_path), sc)
        shown = str(ctrl_path.relative_to(ROOT) if ctrl_path.is_relative_to(ROOT) else ctrl_path)
    metrics = write_report(
        record,
        Path(out) / flight.name,
        controller_path=shown,
        profile_path=str(profile_path.relative_to(ROOT)),
        scenario_desc=sc.description.strip(),
    )
    metrics["after_fast_changes"] = transient_split(record)
    if flight.role == "paper" and flight.controller == "mfc":
        weight = sc.imu_model(profile).first_stage_filter_weight
        metrics.update(motion_limits(record, profile, weight, sc.link, sc.seed))
    return metrics
