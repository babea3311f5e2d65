r"""Fly the outer loops (attitude, vertical, horizontal) on the rate loop, in process.

An outer flight is the product's: :func:`sitl.lab.simulate.simulate_flight` flies
the flight core (:class:`companion.core.FlightCore`) in ``--mode position`` or
``--mode altitude``, as ``companion run`` flies it, on its ideal link:

* the plant (:class:`sitl.physics.Quadrotor`, the scenario's wind) and the IMU,
  from the scenario's seed streams (:func:`sitl.world.flight_streams`);
* the autopilot's estimator (:mod:`sitl.estimator_model`, the scenario's): the
  outer loops see ``ATTITUDE_QUATERNION`` at the IMU rate and
  ``LOCAL_POSITION_NED`` at 50 Hz, with an EKF's errors and lags, never the true
  state; the landed state at :data:`companion.step.LANDED_STATE_RATE_HZ`;
* the flight mode's law (:class:`companion.control.hold_modes.HoldMode`), the
  shipped rate controller behind it, the command gate and the per-sample
  failsafes; the actuator controls, allocated as PX4 allocates them, are held
  until the next sample.

What the scenario asks reaches the product as a user's input would
(:mod:`sitl.lab.outer_plan`): the altitude and position scenarios as a plan the
position mode flies instead of the sticks (as it flies a ``--mission``), the
angle scenario as a pilot's sticks in the altitude mode.

Take-off. The vehicle starts on its legs and engages as the estimates arrive.
The position mode takes off as for a mission whose waypoint is above: only the
vertical loop runs, asking a 1 m/s climb, until the autopilot reports the
vehicle in the air; the plan then climbs its setpoint at 1 m/s to the
scenario's altitude. In the angle scenario the pilot raises the throttle until
that altitude, then centres it (the altitude mode holds where the climb ends).
The scenario's own setpoints start at about :attr:`OuterScenario.start_s`
(``meta["start_s"]``: when they did).

Modes and scenarios (:data:`SCENARIOS`; Python definitions: the YAML
:class:`sitl.scenario.Scenario` needs a pilot and has no setpoints):

* ``angle``: stick-like attitude doublets (roll, pitch, then a heading turn) in
  the altitude mode: the attitude loop with the vertical loop's collective (PX4's
  "altitude" mode; no horizontal loop; the yaw stick asks a rate, so no heading
  error is scored);
* ``altitude``: altitude steps, position held;
* ``position``: position hold in the paper's gusty wind; a 10 m square at 2 m/s
  (moving position setpoint with the velocity as feedforward).

Metrics (:func:`outer_metrics`), from the true state against the setpoints, over
the scored part (from :attr:`OuterScenario.score_from_s`, less the first
:attr:`OuterScenario.step_settle_s` after each altitude step): horizontal and
vertical position RMS error (m), the same against the estimate, attitude MAE
(deg: roll and pitch against what the attitude loop was asked; heading
separately, where one was asked), the time the rate loop's mixer saturated an axis, the time the
collective sat at a bound, and the crash (the plant's).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import PID_DEFAULT_CONTROLLER, MfcConfig, PidConfig, load_controller
from companion.control.outer import DEFAULT_OUTER_GAINS, OuterController, OuterGains, OuterLaw
from companion.core import FlightCore
from companion.profile import VehicleProfile, load_profile
from sitl.estimator_model import EKF_GPS, PERFECT, EstimatorSpec
from sitl.frames import quat_to_euler_rad
from sitl.lab.cascade_pid import PX4_DEFAULT_CASCADE, CascadeGains, CascadePid
from sitl.lab.inprocess import px4_stick_limits
from sitl.lab.outer_plan import (
    AnglePilot,
    CentredSticks,
    ScenarioPath,
    ScenarioPlan,
    Setpoints,
)
from sitl.lab.simulate import simulate_flight
from sitl.physics import Quadrotor
from sitl.rotors import hover_motor_command
from sitl.scenario import ImuOverride, Scenario, WindSpec

__all__ = [
    "MODES",
    "OUTER_LAWS",
    "PAPER_IMU",
    "PAPER_WIND",
    "SCENARIOS",
    "VIBRATION_IMU",
    "OuterFlight",
    "OuterScenario",
    "main",
    "outer_metrics",
    "simulate_outer_flight",
]

MODES = ("angle", "altitude", "position")

OUTER_LAWS = ("mfc", "px4")
"""The outer loops :func:`simulate_outer_flight` can fly: the MFC cascade
(:class:`companion.control.outer.OuterController`) or PX4's default cascaded
baseline (:class:`sitl.lab.cascade_pid.CascadePid`)."""

PAPER_WIND = WindSpec(steady_ned_m_s=(2.0, 0.0, 0.0), gust_sigma_m_s=1.2, gust_length_m=30.0)
"""``sitl/scenarios/paper-acro.yaml``'s wind: 2 m/s from the south, gusts sigma 1.2 m/s."""

PAPER_IMU = ImuOverride(
    rate_hz=250.0, gyro_noise_density_rad_s_sqrt_hz=1.0e-3, first_stage_filter_weight=0.3
)
"""``paper-acro.yaml``'s gyro: the paper's 250 Hz, vibration noise, its first-stage filter.
Not the default here: the outer loops limit-cycle behind it (``docs/research/outer.md``,
step two)."""

VIBRATION_IMU = ImuOverride(gyro_noise_density_rad_s_sqrt_hz=1.0e-3)
"""``hover-gusts.yaml``'s gyro: the profile's (1 kHz, unfiltered) with a small
multirotor's vibration noise (about 1.8 deg/s RMS at 1 kHz) in place of the
datasheet floor."""

TAKEOFF_CLIMB_M_S = 1.0
"""Climb rate asked on the ground and along the take-off ramp, m/s."""


def _hold(up_m: float) -> Callable[[float], Setpoints]:
    return lambda _t: Setpoints(up_m)


def _altitude_steps(
    base_m: float, steps: Sequence[tuple[float, float]]
) -> Callable[[float], Setpoints]:
    """(time after start, altitude) pairs; ``base_m`` before the first."""

    def sp(t: float) -> Setpoints:
        up = base_m
        for t_step, a in steps:
            if t >= t_step:
                up = a
        return Setpoints(up)

    return sp


def _square(up_m: float, side_m: float, speed_m_s: float) -> Callable[[float], Setpoints]:
    """Around a square from the origin, north, east, south, west, at a constant
    speed (position setpoint moving, the velocity as feedforward); then hold."""
    corners = ((0.0, 0.0), (side_m, 0.0), (side_m, side_m), (0.0, side_m), (0.0, 0.0))
    leg_s = side_m / speed_m_s

    def sp(t: float) -> Setpoints:
        if t < 0.0 or t >= 4 * leg_s:
            return Setpoints(up_m)
        i = int(t // leg_s)
        f = (t - i * leg_s) / leg_s
        (n0, e0), (n1, e1) = corners[i], corners[i + 1]
        vel = ((n1 - n0) / leg_s, (e1 - e0) / leg_s)
        return Setpoints(up_m, position_ne_m=(n0 + f * (n1 - n0), e0 + f * (e1 - e0)),
                         velocity_ne_m_s=vel)  # fmt: skip

    return sp


def _figure_eight(
    up_m: float, size_m: float, speed_m_s: float, laps: int = 1
) -> Callable[[float], Setpoints]:
    """A figure eight (a lemniscate of Gerono) through the origin: north
    ``size_m sin(w t)``, east ``size_m / 2 sin(2 w t)``, the velocity and the
    acceleration as feedforward (as a trajectory generator gives them),
    ``speed_m_s`` its fastest (at the crossing: ``w = speed / (size sqrt 2)``);
    ``laps`` times, then a hold."""
    w = speed_m_s / (size_m * math.sqrt(2.0))
    end_s = laps * 2.0 * math.pi / w

    def sp(t: float) -> Setpoints:
        if t < 0.0 or t >= end_s:
            return Setpoints(up_m)
        a = w * t
        return Setpoints(
            up_m,
            position_ne_m=(size_m * math.sin(a), 0.5 * size_m * math.sin(2.0 * a)),
            velocity_ne_m_s=(size_m * w * math.cos(a), size_m * w * math.cos(2.0 * a)),
            accel_ne_m_s2=(
                -size_m * w * w * math.sin(a),
                -2.0 * size_m * w * w * math.sin(2.0 * a),
            ),
        )

    return sp


def _angle_sticks(up_m: float) -> Callable[[float], Setpoints]:
    """Stick-like attitude doublets (symmetric, so the drift they cause cancels):
    roll 15 deg right then left, pitch 15 deg down then up, a faster 25 deg roll
    doublet, then a 90 deg heading turn and back; 1.5 s holds between."""
    d15, d25 = math.radians(15.0), math.radians(25.0)
    seq = (  # (duration s, roll, pitch, yaw)
        (2.0, 0.0, 0.0, 0.0), (1.5, d15, 0.0, 0.0), (1.5, -d15, 0.0, 0.0),
        (2.0, 0.0, 0.0, 0.0), (1.5, 0.0, -d15, 0.0), (1.5, 0.0, d15, 0.0),
        (2.0, 0.0, 0.0, 0.0), (0.8, d25, 0.0, 0.0), (0.8, -d25, 0.0, 0.0),
        (2.0, 0.0, 0.0, 0.0), (3.0, 0.0, 0.0, math.pi / 2), (3.0, 0.0, 0.0, 0.0),
    )  # fmt: skip

    def sp(t: float) -> Setpoints:
        t0 = 0.0
        for dur, r, p, y in seq:
            if t < t0 + dur:
                return Setpoints(up_m, roll_rad=r, pitch_rad=p, yaw_rad=y)
            t0 += dur
        return Setpoints(up_m)

    return sp


@dataclass(frozen=True)
class OuterScenario:
    """One outer-loop flight: what is asked, in what air, with which sensors."""

    name: str
    mode: str
    description: str
    duration_s: float
    setpoints: Callable[[float], Setpoints] = field(repr=False)
    """Setpoints against the time after :attr:`start_s`."""
    hold_up_m: float = 5.0
    """The take-off altitude (and the scenario's first)."""
    start_s: float = 10.0
    """When the scenario's own setpoints start (take-off before)."""
    score_from_s: float = 14.0
    """Metrics from this time on (flight time, s)."""
    wind: WindSpec = PAPER_WIND
    imu: ImuOverride = VIBRATION_IMU
    estimator: EstimatorSpec = EKF_GPS
    seed: int = 20200318
    physics_dt_s: float = 0.001
    step_times_s: tuple[float, ...] = ()
    """Altitude steps (times after :attr:`start_s`): reach times are measured."""
    step_settle_s: float = 5.0
    """After each step, this long is left out of the position RMS (the hold part)."""
    path: bool = False
    """A path is flown: the path error (distance to the planned path, wherever along
    it) is measured while the setpoint moves."""

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode: expected one of {', '.join(MODES)}, got {self.mode!r}")
        if not (self.score_from_s < self.duration_s):
            raise ValueError("score_from_s: must be before the end of the flight")

    def with_duration(self, duration_s: float) -> OuterScenario:
        """The same scenario, shorter or longer (scoring kept where it was, or at
        the last third when that is past the end)."""
        score = self.score_from_s
        if score >= duration_s:
            score = duration_s * 2.0 / 3.0
        return dataclasses.replace(self, duration_s=duration_s, score_from_s=score)


_STEPS = ((0.0, 8.0), (10.0, 4.0), (20.0, 6.0))

SCENARIOS: dict[str, OuterScenario] = {
    s.name: s
    for s in (
        OuterScenario(
            "angle-sticks", "angle",
            "Attitude doublets (roll, pitch 15 and 25 deg, a 90 deg heading turn) at 5 m, "
            "altitude held, in the paper's gusty wind.",
            40.0, _angle_sticks(5.0), score_from_s=10.0,
        ),
        OuterScenario(
            "altitude-steps", "altitude",
            "Altitude 5 -> 8 -> 4 -> 6 m, 10 s apart, position held, in the paper's gusty wind.",
            40.0, _altitude_steps(5.0, _STEPS), score_from_s=10.0,
            step_times_s=tuple(t for t, _ in _STEPS),
        ),
        OuterScenario(
            "position-hold", "position",
            "Position hold at 5 m in the paper's gusty wind (2 m/s from the south, "
            "gusts sigma 1.2 m/s).",
            40.0, _hold(5.0),
        ),
        OuterScenario(
            "square", "position",
            "A 10 m square at 2 m/s (north, east, south, west) at 5 m, then a hold, "
            "in the paper's gusty wind.",
            40.0, _square(5.0, 10.0, 2.0), score_from_s=10.0, path=True,
        ),
        OuterScenario(
            "square-fast", "position",
            "A 20 m square at 5 m/s (north, east, south, west) at 5 m, then a hold, "
            "in the paper's gusty wind.",
            40.0, _square(5.0, 20.0, 5.0), score_from_s=10.0, path=True,
        ),
        OuterScenario(
            "figure-eight", "position",
            "A figure eight 16 m by 8 m at up to 2 m/s (one lap, 36 s) at 5 m, "
            "in the paper's gusty wind.",
            50.0, _figure_eight(5.0, 8.0, 2.0), score_from_s=10.0, path=True,
        ),
        OuterScenario(
            "figure-eight-fast", "position",
            "A figure eight 16 m by 8 m at up to 5 m/s (two laps, 28 s) at 5 m, "
            "in the paper's gusty wind.",
            45.0, _figure_eight(5.0, 8.0, 5.0, laps=2), score_from_s=10.0, path=True,
        ),
    )
}  # fmt: skip
"""The bundled outer-loop scenarios, by name."""

DEFAULT_SCENARIO = {
    "angle": "angle-sticks",
    "altitude": "altitude-steps",
    "position": "position-hold",
}


@dataclass
class OuterFlight:
    """Per-IMU-sample columns of one flight, and what describes it (``meta``).

    Columns: ``t_s``; ``pos_ned_m`` (n, 3) true; ``est_pos_ned_m`` (n, 3) the
    estimate the loops flew on; ``euler_rad`` (n, 3) true;
    ``sp_pos_ne_m``, ``sp_vel_ne_m_s`` (n, 2); ``sp_up_m``; ``sp_att_rad`` (n, 3) what the attitude
    loop was asked (roll, pitch, heading); ``thrust`` collective asked of the rate
    loop; ``thrust_applied`` the mixer's; ``rate_ref_rad_s``, ``gyro_rad_s``,
    ``torque`` (n, 3) the rate loop's reference, measurement and realised torque;
    ``hover_thrust`` the vertical loop's estimate; ``rate_sat`` any rate-loop axis
    saturated; ``thrust_sat``; ``tilt_limited``; ``airborne``; ``est_euler_rad``
    (n, 3) the attitude estimate flown on; ``yaw_share`` yaw's share of roll and
    pitch offered to the mixer (0 for a law without one).
    """

    columns: dict[str, np.ndarray]
    meta: dict[str, Any]


def simulate_outer_flight(
    plant: VehicleProfile,
    rate_controller_cfg: MfcConfig | PidConfig,
    scenario: OuterScenario,
    *,
    seed: int | None = None,
    gains: OuterGains = DEFAULT_OUTER_GAINS,
    duration_s: float | None = None,
    outer_law: str = "mfc",
    cascade_gains: CascadeGains = PX4_DEFAULT_CASCADE,
    gyro_hz: float | None = None,
) -> OuterFlight:
    """Fly ``scenario`` on ``plant`` through the product's flight core (module
    docstring).

    Parameters
    ----------
    plant
        The vehicle (its physics, and the profile the rate controller is given).
    rate_controller_cfg
        The rate loop (``companion.config.load_controller()``: the shipped one).
    scenario
        Mode, setpoints, duration, wind, IMU, estimator.
    seed
        Overrides ``scenario.seed``; everything random derives from it.
    gains
        The outer loops' gains (one set for every vehicle).
    duration_s
        Overrides the scenario's duration (flight time, s).
    outer_law
        ``"mfc"`` (the MFC outer loops with ``gains``) or ``"px4"`` (PX4's default
        cascade, :class:`sitl.lab.cascade_pid.CascadePid` with ``cascade_gains``),
        flown by the same flight mode. The rate loop is ``rate_controller_cfg``
        either way: PX4's whole default cascade is ``outer_law="px4"`` over
        ``load_controller(PID_DEFAULT_CONTROLLER)``.
    cascade_gains
        The baseline's parameters (PX4's defaults).
    gyro_hz
        Fly the core on the gyro as PX4 sends it to a companion at this rate
        (:func:`sitl.lab.simulate.simulate_flight`); default: every IMU sample.
    """
    if outer_law not in OUTER_LAWS:
        raise ValueError(f"outer_law: expected one of {', '.join(OUTER_LAWS)}, got {outer_law!r}")
    seed = scenario.seed if seed is None else seed
    duration = scenario.duration_s if duration_s is None else duration_s
    flown = dataclasses.replace(scenario, duration_s=duration)
    sc = Scenario(
        name=scenario.name, seed=seed, pilot=f"lab:{scenario.name}", duration_s=duration,
        free_flight=True, wind=scenario.wind, imu=scenario.imu,
        physics_dt_s=scenario.physics_dt_s,
    )  # fmt: skip
    law: Callable[[], OuterLaw] | None = None
    if outer_law == "px4":
        law = lambda: CascadePid(cascade_gains)  # noqa: E731
    elif gains != DEFAULT_OUTER_GAINS:
        law = lambda: OuterController(gains)  # noqa: E731
    angle = scenario.mode == "angle"
    plan = None if angle else ScenarioPlan(flown)
    pilot = AnglePilot(flown, px4_stick_limits()[0]) if angle else CentredSticks(duration)
    # Besides what the flight's record already has (t_s, thrust, the rate reference,
    # the torque: taken from it below).
    names = ("pos_ned_m", "est_pos_ned_m", "euler_rad", "sp_pos_ne_m", "sp_vel_ne_m_s",
             "sp_up_m", "sp_att_rad", "thrust_applied", "gyro_rad_s", "hover_thrust",
             "rate_sat", "thrust_sat", "tilt_limited", "airborne", "gain_scale",
             "est_euler_rad", "yaw_share")  # fmt: skip
    cols: dict[str, list[Any]] = {k: [] for k in names}
    seen: dict[str, Any] = {"lift_off_s": None, "start_s": scenario.start_s if angle else None}
    nan2 = (math.nan, math.nan)
    nan3 = (math.nan, math.nan, math.nan)

    def observe(t: float, core: FlightCore, quad: Quadrotor) -> None:
        modes, step = core.modes, core.step
        hold, out, st = modes.hold, step.out, quad.state
        assert hold is not None and modes.pos is not None
        vert = hold.outer.vertical
        if seen["lift_off_s"] is None and not st.landed:
            seen["lift_off_s"] = t
        path = modes.mission_path
        started = isinstance(path, ScenarioPath) and modes.mission_t >= path.start_s
        if seen["start_s"] is None and started:
            seen["start_s"] = t
        # What was asked: the plan's setpoint (on the legs the mode flies only a
        # climb), or the altitude mode's own from the sticks.
        sp = path.at(modes.mission_t) if isinstance(path, ScenarioPath) else hold.setpoint
        ne, up = sp.horizontal.position_ne_m, sp.vertical.up_m
        att = hold.attitude_setpoint
        cols["pos_ned_m"].append(st.pos_ned_m)
        cols["est_pos_ned_m"].append(modes.pos[0])
        cols["euler_rad"].append(quat_to_euler_rad(st.q_wxyz))
        cols["sp_pos_ne_m"].append(nan2 if ne is None else ne)
        cols["sp_vel_ne_m_s"].append(sp.horizontal.velocity_ne_m_s)
        cols["sp_up_m"].append(math.nan if up is None else up)
        if att is None:
            cols["sp_att_rad"].append((0.0, 0.0, math.nan))
        else:
            yaw = math.nan if att.yaw_rad is None else att.yaw_rad
            cols["sp_att_rad"].append((att.roll_rad, att.pitch_rad, yaw))
        cols["thrust_applied"].append(out.thrust)
        cols["gyro_rad_s"].append(step.gyro)
        cols["hover_thrust"].append(vert.hover_thrust)
        cols["rate_sat"].append(any(out.saturated_axes))
        cols["thrust_sat"].append(vert.saturated)
        cols["tilt_limited"].append(hold.tilt_limited)
        cols["airborne"].append(not st.landed)
        cols["gain_scale"].append(hold.outer.gain_scale)
        cols["yaw_share"].append(step.controller.yaw_share.value)
        q = modes.att_q
        cols["est_euler_rad"].append(nan3 if q is None else quat_to_euler_rad(q))
        seen["outer"] = hold.outer

    record = simulate_flight(
        plant, rate_controller_cfg, sc, seed=seed, mode="altitude" if angle else "position",
        mission=plan, outer_law=law, estimator=scenario.estimator, pilot=pilot,
        observe=observe, gyro_hz=gyro_hz,
    )  # fmt: skip
    columns = {k: np.asarray(v, dtype=float) for k, v in cols.items()}
    for k, rec in (("t_s", "t_s"), ("thrust", "thrust"), ("rate_ref_rad_s", "ref_rad_s"),
                   ("torque", "torque")):  # fmt: skip
        columns[k] = np.asarray(record.columns[rec], dtype=float)
    for k in ("rate_sat", "thrust_sat", "tilt_limited", "airborne"):
        columns[k] = columns[k].astype(bool)
    outer = seen.get("outer")
    parts = () if outer is None else (outer.attitude, outer.vertical, outer.horizontal)
    m = record.meta
    meta: dict[str, Any] = {
        "profile": plant.name,
        "scenario": scenario.name,
        "mode": scenario.mode,
        "outer_law": outer_law,
        "seed": seed,
        "duration_s": duration,
        "sim_time_s": m["sim_time_s"],
        "wall_time_s": m["wall_time_s"],
        "crashed": m["crashed"],
        "crashed_at_s": m["crashed_at_s"],
        "lift_off_s": seen["lift_off_s"],
        "start_s": seen["start_s"],
        "imu_rate_hz": m["imu_rate_hz"],
        "gyro_hz": m["gyro_hz"],
        "hover_motor_command": hover_motor_command(plant),
        "hover_thrust_estimate": (None if outer is None else float(outer.vertical.hover_thrust)),
        "outer_nonfinite_events": sum(getattr(p, "nonfinite_events", 0) for p in parts),
        "rate_nonfinite_events": m["nonfinite_events"],
        "failsafes": m["failsafes"],
    }
    return OuterFlight(columns, meta)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _rms_finite(x: np.ndarray) -> float | None:
    """The RMS of the finite values (None: none; an altitude not held yet is NaN)."""
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if len(x) else None


def outer_metrics(flight: OuterFlight, scenario: OuterScenario) -> dict[str, Any]:
    """The flight's figures over its scored part (module docstring).

    ``pos_rms_h_m`` (None in angle mode: nothing holds the position),
    ``pos_rms_v_m``, ``pos_max_h_m`` (the true position against the setpoint);
    ``est_rms_h_m``, ``est_rms_v_m`` (the estimate flown on against the setpoint:
    the loops' own error, without the estimator's); ``att_mae_deg`` (roll and pitch, mean of
    both), ``yaw_mae_deg``, ``rate_sat_s``, ``thrust_sat_s``, ``tilt_limited_s``,
    ``gain_scale_min`` and ``backed_off_s`` (the least scale on the outer gains and
    the time it was below 1), ``yaw_share_s`` (the time yaw was offered a share of
    roll and pitch), ``est_floor_h_m``, ``est_floor_v_m``,
    ``est_floor_att_deg``, ``est_floor_yaw_deg`` (the estimate's own error against
    the truth over the same part: RMS, and the attitude's MAE; the floor under the
    loops' figures), ``crashed``, ``crashed_at_s``; for altitude steps
    ``step_reach_s``: per step, the time after it for the estimated altitude to
    come within 10 % of its size of the new one (None: never).
    """
    c, m = flight.columns, flight.meta
    t = c["t_s"]
    out: dict[str, Any] = {
        "profile": m["profile"], "scenario": m["scenario"], "mode": m["mode"],
        "seed": m["seed"], "crashed": bool(m["crashed"]), "crashed_at_s": m["crashed_at_s"],
        "lift_off_s": m["lift_off_s"], "hover_thrust_estimate": m["hover_thrust_estimate"],
        "hover_motor_command": m["hover_motor_command"],
    }  # fmt: skip
    start = scenario.start_s if m.get("start_s") is None else m["start_s"]
    sel = t >= scenario.score_from_s
    for ts in scenario.step_times_s:
        t0 = start + ts
        sel &= ~((t >= t0) & (t < t0 + scenario.step_settle_s))
    if len(t) < 2 or not sel.any():
        for k in ("pos_rms_h_m", "pos_rms_v_m", "pos_max_h_m", "est_rms_h_m", "est_rms_v_m"):
            out[k] = None
        for k in ("att_mae_deg", "yaw_mae_deg", "path_rms_m", "path_max_m"):
            out[k] = None
        for k in ("est_floor_h_m", "est_floor_v_m", "est_floor_att_deg", "est_floor_yaw_deg"):
            out[k] = None
        out.update(rate_sat_s=None, thrust_sat_s=None, tilt_limited_s=None, step_reach_s=None)
        out.update(gain_scale_min=None, backed_off_s=None, yaw_share_s=None)
        return out
    dt_s = float(np.median(np.diff(t)))
    pos = c["pos_ned_m"][sel]
    dn = pos[:, 0] - c["sp_pos_ne_m"][sel, 0]
    de = pos[:, 1] - c["sp_pos_ne_m"][sel, 1]
    dv = -pos[:, 2] - c["sp_up_m"][sel]
    h = np.hypot(dn, de)
    angle = m["mode"] == "angle"
    out["pos_rms_h_m"] = None if angle else float(np.sqrt(np.mean(h * h)))
    out["pos_max_h_m"] = None if angle else float(h.max())
    out["pos_rms_v_m"] = _rms_finite(dv)
    # The loops' own error: the estimate they flew on against the setpoint.
    est = c["est_pos_ned_m"][sel]
    en = est[:, 0] - c["sp_pos_ne_m"][sel, 0]
    ee = est[:, 1] - c["sp_pos_ne_m"][sel, 1]
    ev = -est[:, 2] - c["sp_up_m"][sel]
    out["est_rms_h_m"] = None if angle else float(np.sqrt(np.mean(en * en + ee * ee)))
    out["est_rms_v_m"] = _rms_finite(ev)
    e = c["euler_rad"][sel]
    sp = c["sp_att_rad"][sel]
    err = np.abs(_wrap(e - sp))
    out["att_mae_deg"] = float(np.degrees(np.mean(err[:, :2])))
    # None where no heading was asked (the altitude mode's yaw stick asks a rate).
    yaw_err = err[:, 2][np.isfinite(err[:, 2])]
    out["yaw_mae_deg"] = float(np.degrees(np.mean(yaw_err))) if len(yaw_err) else None
    # The estimate's own error over the same part: the floor under the loops' figures
    # (no law flies better than what it is told; vertical and attitude).
    est_err = c["est_pos_ned_m"][sel] - pos
    out["est_floor_h_m"] = float(np.sqrt(np.mean(est_err[:, 0] ** 2 + est_err[:, 1] ** 2)))
    out["est_floor_v_m"] = float(np.sqrt(np.mean(est_err[:, 2] ** 2)))
    att_err = np.abs(_wrap(c["est_euler_rad"][sel] - e))
    out["est_floor_att_deg"] = float(np.degrees(np.nanmean(att_err[:, :2])))
    out["est_floor_yaw_deg"] = float(np.degrees(np.nanmean(att_err[:, 2])))
    out["rate_sat_s"] = float(c["rate_sat"][sel].sum() * dt_s)
    out["thrust_sat_s"] = float(c["thrust_sat"][sel].sum() * dt_s)
    out["tilt_limited_s"] = float(c["tilt_limited"][sel].sum() * dt_s)
    out["gain_scale_min"] = float(c["gain_scale"][sel].min())
    out["backed_off_s"] = float((c["gain_scale"][sel] < 1.0).sum() * dt_s)
    out["yaw_share_s"] = float((c["yaw_share"][sel] > 0.0).sum() * dt_s)
    reach: list[float | None] = []
    # On the estimate the loops fly: the truth carries the estimate's slow error
    # (tenths of a metre of height for seconds), which is not the loop's response.
    up = -c["est_pos_ned_m"][:, 2]
    for ts in scenario.step_times_s:
        t0 = start + ts
        i0 = int(np.searchsorted(t, t0))
        # The step itself: the largest change of the setpoint within a tenth of a
        # second (a plan's clock may put it a sample or two from t0).
        near = slice(max(i0 - 100, 1), min(i0 + 100, len(t)))
        jumps = np.abs(np.diff(np.nan_to_num(c["sp_up_m"][near.start - 1 : near.stop])))
        if len(jumps) and jumps.max() > 0.0:
            i0 = near.start + int(np.argmax(jumps))
        if i0 >= len(t):
            reach.append(None)
            continue
        target = c["sp_up_m"][i0]
        size = abs(target - c["sp_up_m"][max(i0 - 1, 0)]) or abs(target - up[i0])
        within = np.nonzero(np.abs(up[i0:] - target) <= 0.1 * size)[0]
        reach.append(float(t[i0 + within[0]] - t0) if len(within) else None)
    out["step_reach_s"] = reach or None
    out["path_rms_m"] = out["path_max_m"] = None
    if scenario.path:
        moving = sel & (np.hypot(*c["sp_vel_ne_m_s"].T) > 0.0)
        if moving.sum() >= 2:
            from sitl.lab.outer_report import segment_distances

            d, _ = segment_distances(c["pos_ned_m"][moving, :2], c["sp_pos_ne_m"][moving][::10])
            out["path_rms_m"] = float(np.sqrt(np.mean(d * d)))
            out["path_max_m"] = float(d.max())
    return out


_ROOT = Path(__file__).resolve().parents[2]
TABLE_PROFILES = ("f450", "f450_cut_props", "tarot650", "x500")


def _profile(name: str) -> VehicleProfile:
    p = Path(name)
    if not (p.suffix in (".yaml", ".yml") or p.exists()):
        for base in (Path("vehicle_profiles"), _ROOT / "vehicle_profiles"):
            if (base / f"{name}.yaml").exists():
                p = base / f"{name}.yaml"
                break
    return load_profile(p, simulated=True)


def _fmt(x: Any, spec: str = ".2f") -> str:
    return "-" if x is None else format(x, spec)


def table_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The vehicle x scenario table (markdown) from :func:`outer_metrics` rows."""
    lines = [
        "| vehicle | scenario | pos RMS h, m | pos RMS v, m | pos max h, m | vs estimate h / v, m "
        "| att MAE, deg | yaw MAE, deg | rate sat, s | thrust sat, s | step reach, s "
        "| hover est. | crash |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        reach = r.get("step_reach_s")
        reach_s = "-" if not reach else " / ".join(_fmt(x, ".1f") for x in reach)
        crash = f"at {r['crashed_at_s']:.1f} s" if r["crashed"] else "no"
        lines.append(
            f"| {r['profile']} | {r['scenario']} | {_fmt(r['pos_rms_h_m'])} "
            f"| {_fmt(r['pos_rms_v_m'])} | {_fmt(r['pos_max_h_m'])} "
            f"| {_fmt(r['est_rms_h_m'])} / {_fmt(r['est_rms_v_m'])} | {_fmt(r['att_mae_deg'])} "
            f"| {_fmt(r['yaw_mae_deg'])} | {_fmt(r['rate_sat_s'], '.1f')} "
            f"| {_fmt(r['thrust_sat_s'], '.1f')} | {reach_s} "
            f"| {_fmt(r['hover_thrust_estimate'], '.3f')} | {crash} |"
        )
    return "\n".join(lines)


_COMPARED = (
    ("pos RMS h, m", "pos_rms_h_m", ".2f"),
    ("pos RMS v, m", "pos_rms_v_m", ".2f"),
    ("pos max h, m", "pos_max_h_m", ".2f"),
    ("att MAE, deg", "att_mae_deg", ".2f"),
    ("yaw MAE, deg", "yaw_mae_deg", ".2f"),
    ("rate sat, s", "rate_sat_s", ".1f"),
    ("thrust sat, s", "thrust_sat_s", ".1f"),
    ("step reach (mean), s", "step_reach_mean_s", ".1f"),
)


def _step_reach_mean(r: dict[str, Any]) -> float | None:
    reach = r.get("step_reach_s")
    if not reach or any(x is None for x in reach):
        return None
    return float(sum(reach) / len(reach))


def _ratio(a: float | None, b: float | None) -> str:
    if a is None or b is None:
        return "-"
    if b == 0.0:
        return "-" if a == 0.0 else "inf"
    return format(a / b, ".2f")


def comparison_markdown(
    rows: Sequence[dict[str, Any]], baseline_rows: Sequence[dict[str, Any]]
) -> str:
    """MFC against the baseline, per vehicle, scenario and metric (markdown): each
    cell ``MFC / baseline (MFC/baseline)``; a ratio below 1 is MFC better (every
    metric here is an error, a time at a limit or a time to reach). The rows of
    both lists are flown in the same order (vehicle, scenario)."""
    head = " | ".join(name for name, _, _ in _COMPARED)
    lines = [
        f"| vehicle | scenario | {head} | crash MFC / baseline |",
        "|---|---|" + "---|" * len(_COMPARED) + "---|",
    ]
    for r, b in zip(rows, baseline_rows, strict=True):
        cells = []
        for _, key, spec in _COMPARED:
            if key == "step_reach_mean_s":
                x, y = _step_reach_mean(r), _step_reach_mean(b)
            else:
                x, y = r[key], b[key]
            cells.append(f"{_fmt(x, spec)} / {_fmt(y, spec)} ({_ratio(x, y)})")
        crash = " / ".join(
            f"at {m['crashed_at_s']:.1f} s" if m["crashed"] else "no" for m in (r, b)
        )
        lines.append(f"| {r['profile']} | {r['scenario']} | " + " | ".join(cells) + f" | {crash} |")
    return "\n".join(lines)


def _variant(sc: OuterScenario, args: argparse.Namespace) -> OuterScenario:
    if args.paper_imu:
        sc = dataclasses.replace(sc, imu=PAPER_IMU)
    if args.perfect_estimator:
        sc = dataclasses.replace(sc, estimator=PERFECT)
    return sc


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m sitl.lab.outer_flight``: one flight's metrics as JSON, or
    (``--table``) every bundled scenario on the paper's four vehicles as markdown."""
    ap = argparse.ArgumentParser(
        prog="python -m sitl.lab.outer_flight", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--profile", default="f450", help="a vehicle_profiles name or a profile path")
    ap.add_argument(
        "--mode", choices=MODES, default=None, help="default: position (or the scenario's)"
    )
    ap.add_argument(
        "--scenario",
        choices=sorted(SCENARIOS),
        default=None,
        help="default: the mode's (angle-sticks, altitude-steps, position-hold)",
    )
    ap.add_argument("--duration", type=float, default=None, help="flight time, s")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument(
        "--controller",
        default=None,
        help="rate-loop config (default: the shipped MFC one; with --outer px4, "
        "PX4's default rate PID, companion/data/pid_px4_default.yaml)",
    )
    ap.add_argument(
        "--outer",
        choices=OUTER_LAWS,
        default="mfc",
        help="the outer loops flown: mfc (default) or px4 (PX4's default cascade, "
        "sitl/lab/cascade_pid.py)",
    )
    ap.add_argument(
        "--baseline",
        choices=("px4",),
        default=None,
        help="with --table: also fly PX4's default cascade (over --baseline-controller) "
        "and print its table and the comparison (MFC / PX4 and their ratio)",
    )
    ap.add_argument(
        "--baseline-controller",
        default=None,
        help="the baseline's rate-loop config (default: PX4's default rate PID)",
    )
    ap.add_argument(
        "--profiles",
        default=",".join(TABLE_PROFILES),
        help="with --table: the vehicles, comma-separated (default: the paper's four)",
    )
    ap.add_argument(
        "--table",
        action="store_true",
        help="all scenarios on f450, f450_cut_props, tarot650, x500 (markdown)",
    )
    ap.add_argument(
        "--paper-imu",
        action="store_true",
        help="fly behind paper-acro's gyro (250 Hz, first-stage filter 0.3) instead",
    )
    ap.add_argument(
        "--perfect-estimator",
        action="store_true",
        help="fly on the true state (at the estimator's rates, no errors, no lag)",
    )
    args = ap.parse_args(argv)
    if args.controller:
        cfg = load_controller(args.controller)
    elif args.outer == "px4":
        cfg = load_controller(PID_DEFAULT_CONTROLLER)
    else:
        cfg = load_controller()
    if args.baseline is not None and not args.table:
        ap.error("--baseline needs --table")
    if args.table:
        base_cfg = load_controller(args.baseline_controller or PID_DEFAULT_CONTROLLER)
        rows, base_rows = [], []
        for prof in (p.strip() for p in args.profiles.split(",") if p.strip()):
            plant = _profile(prof)
            for sc in SCENARIOS.values():
                s = sc if args.duration is None else sc.with_duration(args.duration)
                s = _variant(s, args)
                fl = simulate_outer_flight(plant, cfg, s, seed=args.seed, outer_law=args.outer)
                rows.append(outer_metrics(fl, s))
                if args.baseline is not None:
                    fl = simulate_outer_flight(
                        plant, base_cfg, s, seed=args.seed, outer_law=args.baseline
                    )
                    base_rows.append(outer_metrics(fl, s))
        if args.baseline is None:
            sys.stdout.write(table_markdown(rows) + "\n")
            return 0
        rate = args.controller or ("pid_px4_default.yaml" if args.outer == "px4" else "shipped")
        base_rate = args.baseline_controller or "pid_px4_default.yaml"
        sys.stdout.write(
            f"### {args.outer.upper()} outer loops, rate loop: {rate}\n\n"
            f"{table_markdown(rows)}\n\n"
            f"### Baseline: PX4 default cascade ({args.baseline}), rate loop: {base_rate}\n\n"
            f"{table_markdown(base_rows)}\n\n"
            f"### {args.outer.upper()} / baseline (ratio below 1: {args.outer.upper()} better)\n\n"
            f"{comparison_markdown(rows, base_rows)}\n"
        )
        return 0
    sc = SCENARIOS[args.scenario or DEFAULT_SCENARIO[args.mode or "position"]]
    if args.mode is not None and sc.mode != args.mode:
        ap.error(f"--scenario {sc.name} is a {sc.mode} scenario, not {args.mode}")
    if args.duration is not None:
        sc = sc.with_duration(args.duration)
    sc = _variant(sc, args)
    plant = _profile(args.profile)
    fl = simulate_outer_flight(plant, cfg, sc, seed=args.seed, outer_law=args.outer)
    res = outer_metrics(fl, sc)
    if args.outer != "mfc":
        res["outer_law"] = args.outer
    res["wall_time_s"] = fl.meta["wall_time_s"]
    sys.stdout.write(json.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
