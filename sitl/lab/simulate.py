"""Fly a rate controller against the bundled plant in one process, without MAVLink.

The loop is the companion's, minus MAVLink: every IMU sample goes to the
product's flight core (:class:`companion.core.FlightCore`, engaged as on a PX4:
:mod:`sitl.lab.inprocess`), as ``companion run`` gives it each sample off the
link: the same timestamp checks (``dt`` from the sample stamps, in whole
microseconds), the gyro range gate, the law, the command gate and the
per-sample failsafes. Pilot sticks arrive as RC frames at the scenario's RC
rate, and the gated actuator controls, mixed, are held until the next sample. Through the
scenario's companion link (:mod:`sitl.link_model`) the samples, the RC frames and
the landed state reach the companion late (or twice, or never), the companion
drops samples not newer than the last, and each command acts at the autopilot's
first IMU sample after it arrives, as in the SITL. In a flight mode
(``mode``: angle, altitude, position, a mission) the core flies on the
autopilot's estimates as the SITL streams them: the estimator model's
(:mod:`sitl.estimator_model`, begun at the start as the SITL begins it at
arming), on the schedules ``companion run`` asks for, crossing the link as
float32, ahead of the IMU sample they come with; the stick limits and hover
thrust the SITL's PX4 parameters answer. It is what campaigns run many times in
parallel, and what the MAVLink path is checked against for the same seed,
sample for sample, in every mode.

The plant, its IMU, the wind, the pilot and the estimator are the SITL's own
(:class:`sitl.world.World`, seeded from the scenario as the SITL seeds them),
asked the same things in the same order each physics step.
"""

from __future__ import annotations

import heapq
import itertools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import MfcConfig, PidConfig
from companion.control.mfc import RateController
from companion.control.outer import OuterLaw
from companion.core import FlightCore
from companion.failsafe import FailsafeConfig
from companion.flight_modes import FLIGHT_MODES, FlightMode
from companion.mission import FlightPlan
from companion.profile import VehicleProfile
from companion.records import ControlLog
from companion.records import columns as log_columns
from companion.run_options import RunOptions
from companion.startup import HOLD_POSITION_RATE_HZ
from companion.step import LANDED_STATE_RATE_HZ
from sitl.estimator_model import EKF_GPS, EstimatorModel, EstimatorSpec
from sitl.frames import quat_to_euler_rad
from sitl.lab.inprocess import (
    LabShell,
    LocalPosition,
    attitude_quaternion,
    engaged_core,
    rc_frame,
    start_mode,
)
from sitl.link_model import (
    DOWN,
    ID_EXTENDED_SYS_STATE,
    ID_HIGHRES_IMU,
    ID_RC_CHANNELS,
    ID_SET_ACTUATOR_CONTROL_TARGET,
    UP,
    LinkModel,
)
from sitl.physics import Quadrotor
from sitl.pilot import Pilot
from sitl.px4_control import ControlAllocator, thrust_for_command
from sitl.rotors import hover_motor_command
from sitl.scenario import Scenario
from sitl.streams import MessageStreams, StreamSpec
from sitl.world import Every, World, WorldSpec

__all__ = ["FlightRecord", "GyroMeans", "simulate_flight"]

_ON_GROUND, _IN_AIR = 1, 2  # MAV_LANDED_STATE
_ID_ATTITUDE_QUATERNION = 31
_ID_LOCAL_POSITION_NED = 32


@dataclass
class FlightRecord:
    """Per-control-sample columns of one flight, plus what describes it.

    Columns (arrays of length ``n`` samples unless noted): ``t_s``;
    ``ref_rad_s`` (n, 3) the pilot's commanded rate from the sticks;
    ``meas_rad_s`` (n, 3) the gyro as the controller saw it; ``true_rad_s``
    (n, 3); ``thrust`` pilot collective; ``torque`` (n, 3) realised
    normalised torques; ``u`` (n, 3) law outputs; ``f_hat`` (n, 3);
    ``motors`` (n, n_motors); ``sat_axes`` (n, 3) bool; ``held`` bool;
    ``euler_rad`` (n, 3); ``altitude_m``; ``airborne`` bool.
    """

    columns: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)

    def save(self, path: str) -> None:
        np.savez_compressed(path, allow_pickle=False, **self.columns)


class GyroMeans:
    """The gyro as PX4 sends it to a companion: every ``n``-th sample, the mean of
    the last ``n`` (each sample as itself, to the bit, where ``n`` is 1)."""

    def __init__(self, n: int) -> None:
        if n < 1:
            raise ValueError(f"n: expected at least 1 sample a mean, got {n}")
        self.n = n
        self._sum = [0.0, 0.0, 0.0]
        self._count = 0

    def add(self, gyro: tuple[float, float, float]) -> tuple[float, float, float] | None:
        """Take one sample; the mean when it completes one, else None."""
        if self.n == 1:
            return gyro
        total = self._sum
        total[0] += gyro[0]
        total[1] += gyro[1]
        total[2] += gyro[2]
        self._count += 1
        if self._count < self.n:
            return None
        n = self.n
        self._sum, self._count = [0.0, 0.0, 0.0], 0
        return (total[0] / n, total[1] / n, total[2] / n)


class _Estimates:
    """What the SITL's PX4 streams a flight mode besides the IMU, in its order
    (:meth:`sitl.mavlink_face.MavlinkFace.publish`): ahead of the step's IMU
    sample, the estimator model's position (50 Hz) and attitude (with every
    sample); after it, the landed state its autopilot last detected (at the
    previous step); each on the schedule the companion asks for, begun at
    arming."""

    def __init__(self, model: EstimatorModel, streams: MessageStreams, needs_position: bool):
        self.model = model
        self.streams = streams
        self.needs_position = needs_position
        self.begun = False
        self.landed = True
        """The autopilot's landed state: the vehicle's at its last update."""

    @classmethod
    def for_mode(cls, mode: FlightMode, world: World, rate_hz: float) -> _Estimates | None:
        """The streams a flight mode asks for, the attitude at ``rate_hz`` (the gyro's)."""
        model = world.estimator
        if not mode.needs_attitude or model is None:
            return None
        specs = [
            StreamSpec(_ID_ATTITUDE_QUATERNION, "ATTITUDE_QUATERNION", 0.0, imu_based=True),
            StreamSpec(_ID_LOCAL_POSITION_NED, "LOCAL_POSITION_NED", 0.0),
            StreamSpec(ID_EXTENDED_SYS_STATE, "EXTENDED_SYS_STATE", 0.0),
        ]
        streams = MessageStreams(specs, imu_rate_hz=rate_hz)
        # What companion run's start-up asks for (companion.startup).
        streams.set_interval(_ID_ATTITUDE_QUATERNION, 1e6 / rate_hz)
        if mode.needs_position:
            streams.set_interval(_ID_LOCAL_POSITION_NED, 1e6 / HOLD_POSITION_RATE_HZ)
        streams.set_interval(ID_EXTENDED_SYS_STATE, 1e6 / LANDED_STATE_RATE_HZ)
        return cls(model, streams, mode.needs_position)

    def ahead(self, core: FlightCore, t_s: float, state: Any, *, imu_sample: bool) -> None:
        """The estimator fed this step's state; what goes out ahead of the sample."""
        if self.begun:
            self.model.update(state)
        else:
            self.model.begin(state)
            self.begun = True
        st = self.streams
        att, pos = self.model.attitude, self.model.position
        if st.due(_ID_LOCAL_POSITION_NED, t_s) and pos is not None:
            local = LocalPosition.of(pos.position_ned_m, pos.velocity_ned_m_s)
            core.messages.on_message(local, t_s)
        if imu_sample and st.due(_ID_ATTITUDE_QUATERNION, t_s) and att is not None:
            core.modes.on_attitude_quaternion(attitude_quaternion(t_s, att.q_wxyz))

    def after(self, core: FlightCore, t_s: float, landed: bool) -> None:
        """What goes out after the sample: the landed state the autopilot detected
        at its last update; then it updates on this step's ``landed``."""
        if self.streams.due(ID_EXTENDED_SYS_STATE, t_s):
            core.messages.on_landed_state(_ON_GROUND if self.landed else _IN_AIR)
        self.landed = landed


def simulate_flight(
    plant: VehicleProfile,
    controller_cfg: MfcConfig | PidConfig,
    scenario: Scenario,
    *,
    controller_profile: VehicleProfile | None = None,
    seed: int | None = None,
    progress: Callable[[float], None] | None = None,
    law: RateController | None = None,
    failsafe: FailsafeConfig | None = None,
    control_log: Path | None = None,
    mode: str = "rates",
    mission: FlightPlan | None = None,
    outer_law: Callable[[], OuterLaw] | None = None,
    estimator: EstimatorSpec = EKF_GPS,
    pilot: Pilot | None = None,
    observe: Callable[[float, FlightCore, Quadrotor], None] | None = None,
    gyro_hz: float | None = None,
) -> FlightRecord:
    """Fly ``scenario`` on the ``plant`` with a controller built from ``controller_cfg``.

    Parameters
    ----------
    plant
        The vehicle that is really there (its physics drive the simulation).
    controller_cfg
        The controller configuration (gains, stick curves).
    scenario
        Pilot, duration, wind, IMU overrides, seed.
    controller_profile
        The profile the controller is given (its geometry makes the mixer);
        defaults to ``plant``. Giving another vehicle's profile flies a vehicle
        the controller was not told about.
    seed
        Overrides ``scenario.seed``.
    progress
        Called now and then with the fraction of the flight done.
    law
        A rate controller to fly in place of the one ``controller_cfg`` builds
        (which still gives the stick map and the recorded kind): the lab's
        oracle (:mod:`sitl.lab.oracle`). If it has a ``see_plant`` method, the
        loop calls it with the :class:`~sitl.physics.Quadrotor` (to read, never
        to change) just before each ``update``. The shipped laws have none, so
        their flights are untouched.
    failsafe
        The per-sample failsafes' thresholds (``companion run``'s defaults). A
        failsafe stops the commands, as in the product; the plant's autopilot
        holds the last one (``meta["failsafes"]`` says which fired).
    control_log
        Write the core's control log here, as ``companion run --log-dir`` writes
        ``control.mcap`` (same topics, fields and events; the sample times are
        the plant's, ``wall_s`` the lab's clock), so a simulated flight opens in
        Foxglove and PlotJuggler as a real one does.
    mode, mission
        ``companion run``'s ``--mode`` and ``--mission``. A flight mode flies on
        the autopilot's estimates as the SITL streams them (module docstring);
        on the ideal link only.
    outer_law
        Makes the outer loops the altitude and position modes fly in place of
        their own (the lab's baseline: PX4's default cascade,
        :class:`sitl.lab.cascade_pid.CascadePid`).
    estimator
        The autopilot's estimator a flight mode flies on (its errors and lags).
    pilot
        Flies the sticks in place of ``scenario.pilot`` (which then only names it).
    observe
        Called after each sample the core flew, with its time, the core and the
        plant (to read, never to change): the lab's outer flights record the
        loops' insides.
    gyro_hz
        The core gets the gyro as PX4 sends a companion ``HIGHRES_IMU`` at this
        rate: every ``n``-th IMU sample, the mean of the last ``n`` (``n`` the IMU's
        rate over ``gyro_hz``, rounded, at least 1), as PX4 integrates its gyro
        over ``IMU_INTEG_RATE``'s interval. The IMU, the estimator and the
        autopilot's own output keep the IMU's rate. Default: every sample.
    """
    flight_seed = scenario.seed if seed is None else seed
    dt = scenario.physics_dt_s
    flown = FLIGHT_MODES[mode]
    world = World(
        plant,
        WorldSpec(
            dt_s=dt,
            test_stand=not scenario.free_flight,
            imu_model=scenario.imu_model(plant),
            wind=scenario.wind.config(),
            pilot=scenario.pilot,
            # The pilot's hover collective in PX4's units (0 the motors' armed idle, 1 full).
            hover_throttle=thrust_for_command(hover_motor_command(plant), plant.limits.motor_idle),
            estimator=estimator if flown.needs_attitude else None,
        ),
        flight_seed,
        pilot=pilot,
    )
    quad, imu = world.quad, world.imu
    means = GyroMeans(1 if gyro_hz is None else max(1, round(imu.model.rate_hz / gyro_hz)))
    fed_hz = imu.model.rate_hz / means.n
    assert world.pilot is not None
    duration = scenario.duration_s or world.pilot.duration_s
    opts = RunOptions(
        connect="in-process",
        profile=controller_profile or plant,
        controller=controller_cfg,
        output="actuator",
        engage="auto",
        failsafe=FailsafeConfig() if failsafe is None else failsafe,
        mode=mode,  # type: ignore[arg-type]
        mission=mission,
    )
    estimates = _Estimates.for_mode(flown, world, fed_hz)
    if estimates is not None and not scenario.link.ideal:
        raise ValueError(f"mode {mode!r}: flown in process on the ideal link only")
    shell = LabShell()
    now = [0.0]  # the lab's clock: the plant's time
    log = None
    if control_log is not None:
        log = ControlLog(
            control_log,
            log_columns(opts.profile.n_motors),
            meta={"profile": plant.name, "controller": controller_cfg.kind, "in_process": "1"},
        )
        shell.on_event = lambda kind, detail: log.event(
            {"t_s": now[0], "wall": now[0], "kind": kind, "detail": detail}
        )
    before = None
    if estimates is not None:

        def before(core: FlightCore) -> None:
            start_mode(core, fed_hz, on_ground=quad.state.landed)

    core = engaged_core(
        opts, shell, lambda: now[0], controller=law, outer_law=outer_law, before=before
    )
    row: list[list[float]] = [[]]
    if estimates is not None:
        # A flight mode's collective is the law's, not the pilot's: read back from
        # the control-log row the core builds (and passed on to the log, if one).
        thrust_at = log_columns(opts.profile.n_motors).index("thrust")
        keep = log.append if log is not None else None

        def append(values: list[float]) -> None:
            row[0] = values
            if keep is not None:
                keep(values)

        core.output.log_append = append
    elif log is not None:
        core.output.log_append = log.append
    controller, step, pilot_in = core.controller, core.step, core.pilot
    see_plant = getattr(controller, "see_plant", None)
    autopilot_mix = ControlAllocator.from_profile(plant).mix
    n_motors = plant.n_motors

    n_steps = round(duration / dt)
    # The landed state, as the autopilot streams it at the rate the companion asks:
    # one message at each period (the first at the start), read on its physics step.
    landed_due = Every(1.0 / LANDED_STATE_RATE_HZ)
    rc_due = Every(1.0 / scenario.rc_rate_hz)
    channels: tuple[int, ...] = (1500, 1500, 1000, 1500)
    motors: tuple[float, ...] = (0.0,) * n_motors

    cols: dict[str, list[Any]] = {
        k: []
        for k in (
            "t_s", "ref_rad_s", "meas_rad_s", "true_rad_s", "thrust", "torque", "u", "f_hat",
            "motors", "sat_axes", "held", "euler_rad", "altitude_m", "airborne",
        )
    }  # fmt: skip
    link = LinkModel(scenario.link, scenario.seed if seed is None else seed)
    ideal = scenario.link.ideal
    down_stream = ID_SET_ACTUATOR_CONTROL_TARGET
    # In flight through a link, what is on its way: (arrival, order, what, payload).
    uplink: list[tuple[float, int, int, Any]] = []
    downlink: list[tuple[float, int, tuple[float, ...]]] = []
    order = itertools.count()
    last_sample_t = -math.inf

    def on_landed(landed: bool) -> None:
        core.messages.on_landed_state(_ON_GROUND if landed else _IN_AIR)

    def on_sample(
        sample_t: float, gyro: tuple[float, float, float], arrival: float
    ) -> tuple[float, ...]:
        """The core's step for one sample it received; the motors the autopilot
        makes of the last command it has."""
        if see_plant is not None:
            see_plant(quad)
        n = core.n_imu
        core.on_imu(sample_t, gyro, arrival)
        if core.n_sample_errors:
            raise RuntimeError(f"the flight core's step raised at t={sample_t:.6f} s")
        if core.n_imu == n:
            return motors  # not flown (the core's timestamp checks)
        controls = shell.controls
        if controls is None:
            return motors
        # The autopilot allocates the controls it is sent (PX4's allocation, as the
        # SITL's PX4 personality does), whatever the law's own mix was.
        c_roll, c_pitch, c_yaw, c_thrust = controls[:4]
        sent = autopilot_mix(c_thrust, c_roll, c_pitch, c_yaw)
        out = step.out
        st = quad.state
        cols["t_s"].append(sample_t)
        cols["ref_rad_s"].append(step.law_ref)
        cols["meas_rad_s"].append(gyro)
        cols["true_rad_s"].append(st.rate_frd_rad_s)
        cols["thrust"].append(pilot_in.thrust if estimates is None else row[0][thrust_at])
        cols["torque"].append(out.torque)
        cols["u"].append(out.u)
        cols["f_hat"].append(out.f_hat)
        cols["motors"].append(out.motors)
        cols["sat_axes"].append(out.saturated_axes)
        cols["held"].append(out.held)
        cols["euler_rad"].append(quat_to_euler_rad(st.q_wxyz))
        cols["altitude_m"].append(-st.pos_ned_m[2])
        cols["airborne"].append(not st.landed)
        if observe is not None:
            observe(sample_t, core, quad)
        return sent

    wall0 = time.perf_counter()
    crashed_at: float | None = None
    report_every = max(1, n_steps // 100)
    for k in range(n_steps):
        t = now[0] = quad.t_s
        if rc_due.due(t):
            channels = world.sticks(t)
            if ideal:
                core.on_rc(rc_frame(channels), t)
            else:
                for a in link.arrivals(UP, ID_RC_CHANNELS, t):
                    heapq.heappush(uplink, (a, next(order), ID_RC_CHANNELS, channels))
        sample = world.sense()
        gyro = None if sample is None else means.add(sample.gyro_frd_rad_s)
        if estimates is not None:
            # As the SITL streams to a flight mode: the estimates, the IMU sample
            # (flown on them), then the landed state.
            estimates.ahead(core, t, quad.state, imu_sample=gyro is not None)
            if sample is not None and gyro is not None:
                motors = on_sample(sample.time_s, gyro, t)
            estimates.after(core, t, quad.state.landed)
        elif ideal:
            # The landed state goes out on its step, ahead of that step's IMU sample
            # (the SITL streams it after arming, every period, as the link branch).
            if landed_due.due(t):
                on_landed(quad.state.landed)
            if sample is not None and gyro is not None:
                motors = on_sample(sample.time_s, gyro, t)
        else:
            if landed_due.due(t):
                for a in link.arrivals(UP, ID_EXTENDED_SYS_STATE, t):
                    heapq.heappush(
                        uplink, (a, next(order), ID_EXTENDED_SYS_STATE, quad.state.landed)
                    )
            if sample is not None and gyro is not None:
                payload = (sample.time_s, gyro)
                for a in link.arrivals(UP, ID_HIGHRES_IMU, t):
                    heapq.heappush(uplink, (a, next(order), ID_HIGHRES_IMU, payload))
            while uplink and uplink[0][0] <= t + 1e-12:
                arrived, _, what, payload = heapq.heappop(uplink)
                if what == ID_RC_CHANNELS:
                    core.on_rc(rc_frame(payload), arrived)
                elif what == ID_EXTENDED_SYS_STATE:
                    on_landed(payload)
                elif payload[0] > last_sample_t:  # the companion drops duplicates and late samples
                    last_sample_t = payload[0]
                    sent = on_sample(payload[0], payload[1], arrived)
                    for a in link.arrivals(DOWN, down_stream, arrived):
                        heapq.heappush(downlink, (a, next(order), sent))
            # The autopilot acts on the newest command at its next IMU sample (its
            # output runs on the gyro loop, as the SITL's does): a command that
            # arrives between two samples waits for the next.
            if sample is not None:
                while downlink and downlink[0][0] <= t + 1e-12:
                    motors = heapq.heappop(downlink)[2]
        quad.step(motors)
        if quad.crashed:
            crashed_at = quad.t_s
            break
        if progress is not None and k % report_every == 0:
            progress(k / n_steps)
    wall = time.perf_counter() - wall0
    if log is not None:
        log.close()
    if progress is not None:
        progress(1.0)
    columns = {k: np.asarray(v) for k, v in cols.items()}
    meta = {
        "profile": plant.name,
        "controller_profile": (controller_profile or plant).name,
        "controller": controller_cfg.kind,
        "scenario": scenario.name,
        "seed": scenario.seed if seed is None else seed,
        "duration_s": duration,
        "sim_time_s": quad.t_s,
        "wall_time_s": wall,
        "crashed": quad.crashed,
        "crashed_at_s": crashed_at,
        "nonfinite_events": controller.nonfinite_events,
        "dt_clamped_events": controller.dt_clamped_events,
        "imu_rate_hz": imu.model.rate_hz,
        "gyro_hz": fed_hz,
        "link": scenario.link.describe(),
        "link_counts": link.counts(),
        "n_motors": n_motors,
        "hover_throttle": world.spec.hover_throttle,
        "failsafes": [f"{kind}: {detail}" for kind, detail in shell.failsafes],
    }
    return FlightRecord(columns, meta)
