"""The SITL simulation loop: physics + IMU + pilot + autopilot + MAVLink face + clocks + log.

One step of the loop (physics ``dt_s`` = 1 ms)::

    read MAVLink (commands, setpoints)        face.poll
    pilot sticks (RC frame every 10 ms)       world.sticks
    IMU sample of the state at t              world.sense
    the estimator's newest output             estimator.update (attitude, position)
    send what is due at t                     face.publish (HIGHRES_IMU, ATTITUDE, ...)
    lockstep: wait for the client's setpoint  face.wait_readable + poll
    autopilot on the IMU sample               autopilot.update -> motor commands
    log the true state at t                   LogWriter.append
    advance the physics to t + dt             quad.step

Clocks
------
``realtime``
    Simulation time is paced to the wall clock; streams flow whatever the client does.
``lockstep``
    In OFFBOARD, after each HIGHRES_IMU sent, the loop waits for the next
    ``SET_ACTUATOR_CONTROL_TARGET`` / ``SET_ATTITUDE_TARGET`` (up to
    ``lockstep_timeout_s`` of wall time) before applying it in the same step and
    stepping on: deterministic and as fast as the client allows. After a timeout
    it stops waiting (the client is taken as gone) until a setpoint arrives again,
    so a disconnected client cannot stall the simulation; the offboard-loss
    failsafe then fires in simulation time. Outside OFFBOARD it never waits and
    runs as fast as the CPU allows, so a client may fall behind there; a client
    that stamps its setpoints with their samples' times (the companion) has its
    late answers to older samples handled but not counted (:mod:`sitl.answers`):
    each wait ends on the answer to the sample it gave. Once a client streams
    setpoints outside OFFBOARD (PX4 wants them before it switches), the clock
    keeps to the wall's (as ``realtime``) until OFFBOARD or
    ``_STREAMING_S`` after the last one, and so it does for ``_COMMANDING_S``
    after each command (a client setting the autopilot up: stream rates, mode,
    arming). Run free there, it would overfill the client's socket: the
    datagrams the kernel drops leave jumps in the IMU time that the wall clock
    does not take, and a client that holds such a sample back as a possibly
    corrupt stamp (the companion does) never answers the one the first wait in
    OFFBOARD is for; a command's COMMAND_ACK may be dropped with them, every
    time it is tried (seen on a loaded machine: a companion gave up on its
    SET_MESSAGE_INTERVAL while the clock ran ten times the wall's). With
    ``autopilot="ardupilot"`` the same holds in GUIDED / GUIDED_NOGPS after
    each RAW_IMU / SCALED_IMU / HIGHRES_IMU sent.

Link
----
``link`` (``--link``, :mod:`sitl.link_model`) puts the companion link between
the autopilot and the socket: what the face sends reaches the socket, and what
it reads is handled, when the link delivers it (delay, jitter, loss,
duplicates, reordering), from the run's seed and in simulation time. The
lockstep clock then waits after the link *delivers* a clock-stream sample newer
than any before (a client drops duplicates and late samples without answering;
a lost sample is not waited for), until as many setpoints as new samples have
reached the socket; each such setpoint counts as sent when its sample arrived,
and is handled when the link delivers it. The link's model starts again at the
pilot's start (with ``pilot_from_arm``, at arming), as the wind, IMU and pilot
streams do. With the ideal link (the default) nothing is queued.

Estimator
---------
The faces stream what the autopilot estimates, not the true state: ATTITUDE,
ATTITUDE_QUATERNION and LOCAL_POSITION_NED carry the newest output of an
:class:`~sitl.estimator_model.EstimatorModel` (``estimator``, by default
:data:`~sitl.estimator_model.EKF_GPS`: an EKF's errors, lag and rate), fed the
true state every physics step and seeded from the run's seed through
:func:`~sitl.estimator_model.estimator_seed_sequence`, a stream of its own: the
plant, IMU, wind, pilot and link draw exactly what they drew before, so the
flight (body rates, motors) is the same bit for bit. Like the wind, IMU and
pilot streams it starts again at the pilot's start (with ``pilot_from_arm``, at
arming), its first estimates then delivered at once
(:meth:`~sitl.estimator_model.EstimatorModel.begin`: the vehicle sits still
until then), so the estimates streamed after arming do not depend on when that was.
They go out ahead of the IMU sample of their step (LOCAL_POSITION_NED, then
ATTITUDE_QUATERNION): a client flies that sample on them, the first one too.
``estimator=None`` (``sitl run --true-state``) streams the true state at every
step instead, as before. The autopilot's own angle and climb-rate loops still
fly on the truth. The log holds the true state.

Autopilot, firmware and parameters
----------------------------------
``autopilot`` picks the personality, ``firmware`` the version its face reports
(PX4: 1.13.3 by default, and from 1.14 ``SET_ACTUATOR_CONTROL_TARGET`` is
dropped, ``sitl.px4_face``; ArduPilot: 4.7.0-dev). ``px4_params`` /
``ardupilot_params`` are set at boot, after the SITL airframe's own settings
(PX4: ``sitl.px4_params.px4_sitl_airframe``; ArduPilot: ``SITL_RATE_TUNE`` and
``SITL_AIRFRAME`` of ``sitl.ardupilot_params``), so they win; any name of the
stack's table is accepted. Read at boot: PX4 ``MAV_SYS_ID`` / ``MAV_COMP_ID``
and ArduPilot ``MAV_SYSID`` (the face's ids), PX4 ``IMU_GYRO_RATEMAX`` (the
fastest IMU stream) and ArduPilot ``SCHED_LOOP_RATE``. PX4 ``COM_OF_LOSS_T``
given as a parameter wins over ``offboard_timeout_s``.

Outcome
-------
A run ends with ``status`` ``"completed"`` (duration reached), ``"stopped"``
(SIGINT/SIGTERM) or ``"crashed"`` (the physics reported a crash; the flight ends
there). All three are normal outcomes (exit code 0); the status is in the summary.

Log
---
``--log FILE`` (e.g. ``flight.npz``) writes the true state per physics step and
the events (``sitl.flight_log`` describes the format); read both back with
:func:`sitl.flight_log.read_log`. Faults to inject: ``sitl.faults``.
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from companion.profile import ImuModel, VehicleProfile
from sitl.autopilot import Autopilot, AutopilotConfig, Joystick
from sitl.estimator_model import EKF_GPS, EstimatorSpec
from sitl.faults import IMU_RANGE_GYRO_RAD_S, Fault, OutgoingFaults
from sitl.flight_log import LogWriter
from sitl.frames import quat_to_euler_rad
from sitl.link_model import LINK_PROFILES, LinkModel, LinkSpec
from sitl.mavlink_face import MavlinkFace
from sitl.mavlink_link import Endpoint, enable_signing
from sitl.personality import Event, FirmwareVersion, ParamStore, Personality
from sitl.px4_control import thrust_for_command
from sitl.px4_face import Px4Face, px4_streams
from sitl.px4_modes import FlightMode, MainMode
from sitl.px4_params import PX4_DEFAULT_FIRMWARE, Px4Params, px4_sitl_airframe
from sitl.rotors import hover_motor_command
from sitl.streams import MessageStreams
from sitl.wind import WindConfig
from sitl.world import Every, World, WorldSpec

__all__ = ["RunConfig", "RunSummary", "Runner", "joystick_from_channels"]

logger = logging.getLogger(__name__)

Status = Literal["completed", "stopped", "crashed"]

_MODE_BY_NAME = {m.name: m for m in MainMode}
RC_PERIOD_S = 0.01
"""The simulated RC receiver delivers a frame every 10 ms (100 Hz)."""
_KEEP_ALIVE_POLL_S = 0.25
"""A lockstep wait looks this often (wall clock) whether a heartbeat is due."""
_STREAMING_S = 0.1
"""A client whose last setpoint is this recent (simulation time) streams them."""
_COMMANDING_S = 1.0
"""A client whose last command is this recent (simulation time) is setting the
autopilot up, waiting for each answer (the companion tries a command four times,
0.5 s apart)."""
PILOT_END_GRACE_S = 2.0
"""With ``pilot_from_arm``, the flight goes on this long after the pilot's timeline
ends (the pilot holds its last segment), so a companion flying the same duration
from its own engagement finishes and hands back before the SITL stops."""


@dataclass(frozen=True)
class RunConfig:
    """Everything a run needs besides the vehicle profile.

    Attributes
    ----------
    mavlink
        Where the MAVLink face sends / listens.
    pilot
        A maneuver name or a stick-script path, or None (no RC).
    seed
        Seed of the one ``np.random.default_rng`` all randomness is spawned from.
    clock
        ``"realtime"`` or ``"lockstep"``.
    duration_s
        Simulated seconds to run; None: the pilot's duration, or until a signal.
    test_stand
        Vehicle on a gimbal rig (attitude free, position held).
    wind_gust_m_s
        Turbulence intensity (per-axis sigma), m/s.
    log_path
        ``.npz`` log to write (plus its ``.events.jsonl``), or None.
    offboard_timeout_s
        Offboard-loss timeout (PX4 ``COM_OF_LOSS_T``; a ``COM_OF_LOSS_T`` in
        ``px4_params`` wins), s.
    lockstep_timeout_s
        Longest wall-clock wait for a setpoint in lockstep, s.
    initial_mode
        Mode at boot by name (``"MANUAL"``, ``"ACRO"``...); None: ACRO with a pilot
        (the pilot flies rates), MANUAL without.
    auto_arm
        Arm at t = 0 when a pilot is given (a human would arm before flying).
    dt_s
        Physics step, s.
    wind
        Steady wind and gusts; overrides ``wind_gust_m_s`` when given.
    imu_model
        The IMU model to use instead of the profile's (scenario overrides).
    rc_period_s
        Interval between RC frames from the pilot, s.
    autopilot
        Personality: ``"px4"`` (:mod:`sitl.autopilot`) or ``"ardupilot"``
        (:mod:`sitl.ardupilot`, ArduCopter-like).
    prearm_fail
        ArduPilot personality: a pre-arm check that fails with this text.
    ardupilot_params
        ArduPilot personality: parameters set at boot, ``(name, value)`` pairs.
    px4_params
        PX4 personality: parameters of :class:`sitl.px4_params.Px4Params` set at
        boot, ``(name, value)`` pairs.
    firmware
        The version the face reports; None: the stack's default (PX4 1.13.3,
        ArduCopter 4.7.0-dev).
    position
        The autopilot has a position estimate (GPS, flow...): False for a vehicle
        without one (no LOCAL_POSITION_NED; hold modes refused).
    rc
        The autopilot has a radio: False for a vehicle flown without one (the
        pilot's timeline still runs, but no sticks reach the autopilot and
        RC_CHANNELS carries no channels, as after ``rc-lost``).
    pilot_input
        How the pilot's sticks reach the autopilot: ``"rc"`` a radio (RC_CHANNELS);
        ``"joystick"`` (PX4 only) a ground station's ``MANUAL_CONTROL`` at the RC
        rate, as PX4 SIH is flown: no RC receiver (no RC_CHANNELS), the pilot's
        channel 5 as aux1; ``rc-lost`` stops the joystick.
    ekf_warmup_s
        ArduPilot: ``(alt_s, pos_s)`` after boot at which its EKF has an altitude
        and a position estimate (arming refused before, as ArduCopter does); None:
        both at boot.
    link
        The companion link (:mod:`sitl.link_model`): what it does to every frame
        sent and read; the ideal link by default.
    estimator
        What the autopilot's estimator streams (:mod:`sitl.estimator_model`):
        ATTITUDE, ATTITUDE_QUATERNION and LOCAL_POSITION_NED carry its output;
        None: the true state, at every step (``--true-state``).
    signing_key
        MAVLink 2 signing key (32 bytes): sign everything sent, accept only
        validly signed frames.
    faults
        Faults to inject (:func:`sitl.faults.parse_fault`), each once at its time, counted
        from the pilot's start (so from arming with ``pilot_from_arm``).
    pilot_from_arm
        Run the pilot's timeline from the moment the vehicle is armed (a
        companion that engages later still flies the whole maneuver list);
        before that the pilot holds the timeline's first sticks. ``duration_s``
        and fault times then count from arming too.
    """

    mavlink: Endpoint
    pilot: str | None = None
    seed: int = 0
    clock: Literal["realtime", "lockstep"] = "realtime"
    duration_s: float | None = None
    test_stand: bool = False
    wind_gust_m_s: float = 0.0
    log_path: Path | None = None
    offboard_timeout_s: float = 1.0
    lockstep_timeout_s: float = 0.5
    initial_mode: str | None = None
    auto_arm: bool = True
    dt_s: float = 0.001
    wind: WindConfig | None = None
    imu_model: ImuModel | None = None
    rc_period_s: float = RC_PERIOD_S
    pilot_from_arm: bool = False
    faults: tuple[Fault, ...] = ()
    signing_key: bytes | None = None
    autopilot: Literal["px4", "ardupilot"] = "px4"
    prearm_fail: str | None = None
    ardupilot_params: tuple[tuple[str, float], ...] = ()
    px4_params: tuple[tuple[str, float], ...] = ()
    firmware: FirmwareVersion | None = None
    position: bool = True
    rc: bool = True
    pilot_input: Literal["rc", "joystick"] = "rc"
    ekf_warmup_s: tuple[float, float] | None = None
    link: LinkSpec = LINK_PROFILES["ideal"]
    estimator: EstimatorSpec | None = EKF_GPS


@dataclass
class RunSummary:
    """How a run went (also stored in the log)."""

    status: Status = "completed"
    seed: int = 0
    clock: str = "realtime"
    profile: str = ""
    pilot: str | None = None
    test_stand: bool = False
    sim_time_s: float = 0.0
    wall_time_s: float = 0.0
    steps: int = 0
    steps_per_wall_s: float = 0.0
    realtime_factor: float = 0.0
    max_lag_s: float = 0.0
    lockstep_waits: int = 0
    lockstep_timeouts: int = 0
    stale_setpoints: int = 0
    setpoints_received: int = 0
    rejected_setpoints: int = 0
    messages_sent: int = 0
    messages_received: int = 0
    final_mode: str = ""
    armed_at_end: bool = False
    link: str = ""
    link_counts: dict[str, int] = field(default_factory=dict)
    setpoint_age_ms: dict[str, float] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)


def joystick_from_channels(chans: tuple[int, ...]) -> Joystick:
    """The pilot's AETR channels (us) as a ground station's ``MANUAL_CONTROL``: ``y`` roll
    and ``r`` yaw ``2 (ch - 1500)``, ``x`` pitch ``-2 (ch2 - 1500)`` (a high pitch
    channel is nose up, stick back), ``z`` ``ch3 - 1000``; channels 5..10, where given,
    as aux1..aux6 (``enabled_extensions`` bits 2..7)."""

    def stick(us: int) -> int:
        return max(-1000, min(1000, 2 * (us - 1500)))

    aux = [0] * 6
    ext = 0
    for i in range(6):
        if 4 + i < len(chans):
            aux[i] = stick(chans[4 + i])
            ext |= 4 << i
    return Joystick(
        x=-stick(chans[1]),
        y=stick(chans[0]),
        z=max(0, min(1000, chans[2] - 1000)),
        r=stick(chans[3]),
        enabled_extensions=ext,
        aux=(aux[0], aux[1], aux[2], aux[3], aux[4], aux[5]),
    )


def _mavlink_id(params: ParamStore, name: str) -> int:
    """A MAVLink system / component id parameter, checked (1..254)."""
    value = int(params[name])
    if not 1 <= value <= 254:
        raise ValueError(f"{name} {value}: a MAVLink id is 1..254")
    return value


@contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT/SIGTERM set ``stop`` instead of killing the loop (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: object) -> None:
        logger.info("signal %d: stopping", signum)
        stop.set()

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


class Runner:
    """One simulated flight: build everything from a profile and a :class:`RunConfig`.

    Nothing touches the network before :meth:`run`.
    """

    def __init__(
        self, profile: VehicleProfile, config: RunConfig, *, profile_name: str = ""
    ) -> None:
        self.profile = profile
        self.config = config
        self.profile_name = profile_name or profile.name
        for fault in config.faults:
            if fault.kind == "motor-fail" and not 0 <= fault.arg < profile.n_motors:
                raise ValueError(
                    f"fault motor-fail@{fault.t_s:g}:{fault.arg}: MOTOR is 0.."
                    f"{profile.n_motors - 1} on {self.profile_name}"
                )
        try:
            hover = hover_motor_command(profile)
        except ValueError:
            hover = 0.5
        if config.autopilot == "px4":
            # PX4's collective runs from the motors' armed idle (0) to full (1).
            self.hover_thrust = thrust_for_command(hover, profile.limits.motor_idle)
        else:
            self.hover_thrust = hover
        wind = config.wind
        if wind is None and config.wind_gust_m_s > 0.0:
            wind = WindConfig(gust_sigma_m_s=config.wind_gust_m_s)
        spec = WorldSpec(
            dt_s=config.dt_s,
            test_stand=config.test_stand,
            imu_model=config.imu_model or profile.physics.imu,
            wind=wind,
            pilot=config.pilot,
            hover_throttle=self.hover_thrust,
            estimator=config.estimator,
        )
        self.world = World(profile, spec, config.seed)
        self.quad = self.world.quad
        self.autopilot: Personality[Any]
        self.face: MavlinkFace[Any]
        self.streams: MessageStreams
        if config.autopilot == "ardupilot":
            self._make_ardupilot(hover)
        else:
            self._make_px4(self.hover_thrust)
        self.autopilot.position_valid = config.position
        self.face.rc_lost = not config.rc
        if config.pilot_input == "joystick":
            if config.autopilot != "px4":
                raise ValueError("a joystick pilot (MANUAL_CONTROL) needs the PX4 personality")
            self.face.rc_fitted = False  # PX4 SIH: no receiver, no RC_CHANNELS
        if config.signing_key is not None:
            enable_signing(self.face.mav, config.signing_key)
        self._link_counts: dict[str, int] = {}
        self.link: LinkModel | None = None
        self._make_link()
        self._outgoing: OutgoingFaults | None = None
        self.stop = threading.Event()
        self.duration_s = config.duration_s
        if self.duration_s is None and self.world.pilot is not None and not config.pilot_from_arm:
            self.duration_s = self.world.pilot.duration_s

    def _make_px4(self, hover_thrust: float) -> None:
        """The PX4 personality (the default)."""
        cfg = self.config
        if cfg.initial_mode is not None:
            if cfg.initial_mode.upper() not in _MODE_BY_NAME:
                raise ValueError(f"PX4 has no mode {cfg.initial_mode!r}")
            main = _MODE_BY_NAME[cfg.initial_mode.upper()]
        else:
            main = MainMode.ACRO if self.world.pilot is not None else MainMode.MANUAL
        params = Px4Params(cfg.firmware or PX4_DEFAULT_FIRMWARE)
        ap = Autopilot(
            self.profile,
            AutopilotConfig(
                offboard_timeout_s=cfg.offboard_timeout_s,
                test_stand=cfg.test_stand,
                hover_thrust=min(max(hover_thrust, 0.05), 0.95),
            ),
            initial_mode=FlightMode(main),
            params=params,
        )
        imu_rate_hz = min(self.world.imu.model.rate_hz, 1.0 / cfg.dt_s)
        for name, value in (*px4_sitl_airframe(imu_rate_hz), *cfg.px4_params):
            if name not in params:
                raise ValueError(
                    f"PX4 parameter {name!r} is not modelled: expected one of "
                    f"{', '.join(params.names)}"
                )
            params.set(name, value)
        # IMU_GYRO_RATEMAX caps the gyro rate PX4 publishes: no IMU stream goes faster.
        gyro_max_hz = params["IMU_GYRO_RATEMAX"]
        if 0 < gyro_max_hz < round(imu_rate_hz):
            imu_rate_hz = gyro_max_hz
        self.autopilot = ap
        self.streams = px4_streams(imu_rate_hz)
        self.face = Px4Face(
            cfg.mavlink,
            ap,
            self.streams,
            sysid=_mavlink_id(params, "MAV_SYS_ID"),
            compid=_mavlink_id(params, "MAV_COMP_ID"),
            firmware=params.firmware,
        )

    def _make_ardupilot(self, hover_motor_cmd: float) -> None:
        """The ArduCopter personality (``--autopilot ardupilot``)."""
        from sitl.ardupilot import ArduCopter, ArduCopterConfig
        from sitl.ardupilot_face import ArduPilotFace, ardupilot_streams
        from sitl.ardupilot_modes import CopterMode
        from sitl.ardupilot_params import SITL_AIRFRAME

        cfg = self.config
        if cfg.initial_mode is not None:
            try:
                mode = CopterMode[cfg.initial_mode.upper()]
            except KeyError:
                raise ValueError(f"ArduCopter has no mode {cfg.initial_mode!r}") from None
        else:
            mode = CopterMode.ACRO if self.world.pilot is not None else CopterMode.STABILIZE
        ap = ArduCopter(
            self.profile,
            ArduCopterConfig(
                test_stand=cfg.test_stand,
                hover_motor_cmd=min(max(hover_motor_cmd, 0.05), 0.95),
                prearm_fail=cfg.prearm_fail,
                params=(*SITL_AIRFRAME, *cfg.ardupilot_params),
                ekf_alt_ready_s=cfg.ekf_warmup_s[0] if cfg.ekf_warmup_s else 0.0,
                ekf_position_ready_s=cfg.ekf_warmup_s[1] if cfg.ekf_warmup_s else 0.0,
            ),
            initial_mode=mode,
        )
        from sitl.ardupilot_face import ARDUPILOT_DEFAULT_FIRMWARE

        streams = ardupilot_streams(ap.loop_rate_hz)
        self.autopilot = ap
        self.streams = streams
        self.face = ArduPilotFace(
            cfg.mavlink,
            ap,
            streams,
            sysid=_mavlink_id(ap.params, "MAV_SYSID"),
            firmware=cfg.firmware or ARDUPILOT_DEFAULT_FIRMWARE,
        )
        # ArduPilot's RC_CHANNELS go on with the last values after the radio is lost.
        self.face.rc_lost_freezes = True

    def run(self) -> RunSummary:
        """Fly until the duration, a signal, or a crash; write the log.

        Raises
        ------
        OSError
            If the MAVLink socket cannot be opened.
        """
        cfg = self.config
        log = LogWriter(self.profile.n_motors, cfg.log_path)
        summary = RunSummary(
            seed=cfg.seed,
            clock=cfg.clock,
            profile=self.profile_name,
            pilot=cfg.pilot,
            test_stand=cfg.test_stand,
        )
        wall0 = time.monotonic()
        # The handler stays until the log is written: a signal that lands while it
        # is written (a driver stopping the run) must not leave it half done.
        with _stop_on_signals(self.stop):
            self._run(log, summary, wall0)
        logger.info(
            "run %s: %.2f s simulated in %.2f s wall (%.1fx), %d steps",
            summary.status,
            summary.sim_time_s,
            summary.wall_time_s,
            summary.realtime_factor,
            summary.steps,
        )
        return summary

    def _run(self, log: LogWriter, summary: RunSummary, wall0: float) -> None:
        cfg = self.config
        if cfg.clock == "realtime":
            # TIMESYNC answers the time the simulation keeps to, not where it is.
            self.face.timesync_clock = lambda: time.monotonic() - wall0
        try:
            with self.face:
                summary.status = self._loop(log, summary, wall0)
        finally:
            wall = time.monotonic() - wall0
            ap = self.autopilot
            summary.sim_time_s = self.quad.t_s
            summary.wall_time_s = wall
            summary.steps_per_wall_s = summary.steps / wall if wall > 0 else 0.0
            summary.realtime_factor = summary.sim_time_s / wall if wall > 0 else 0.0
            summary.setpoints_received = self.face.setpoints_received
            summary.stale_setpoints = self.face.stale_setpoints
            summary.rejected_setpoints = ap.rejected_setpoints
            summary.messages_sent = self.face.messages_sent
            summary.messages_received = self.face.messages_received
            summary.final_mode = ap.mode.name
            summary.armed_at_end = ap.armed
            summary.link = cfg.link.describe()
            summary.link_counts = self._counts_of_link()
            summary.setpoint_age_ms = self.face.setpoint_age_ms()
            for ev in ap.drain_events():
                log.event(ev)
            log.close(asdict(summary))

    def _make_link(self, t_start_s: float | None = None) -> None:
        """The link's model from the run's seed: at start-up, and again at the pilot's
        start ``t_start_s`` (as the world's streams begin again,
        :meth:`~sitl.world.World.restart`), so its draws do not depend on how many
        frames went out before.

        At the pilot's start the flight begins afresh, as the in-process
        simulation's does: the samples and setpoints on their way are lost, and
        an autopilot under external control holds a neutral setpoint (motors at
        idle) until the first answer of the flight arrives.
        """
        spec = self.config.link
        if spec.ideal:
            return
        self._link_counts = self._counts_of_link()
        self.link = LinkModel(spec, self.config.seed)
        self.face.set_link(self.link, restart=t_start_s is not None)
        if t_start_s is not None and self.autopilot.external_control:
            self.face.neutral_setpoint(t_start_s)

    def _counts_of_link(self) -> dict[str, int]:
        """Frames sent, lost and duplicated by the link over the whole run."""
        if self.link is None:
            return dict(self._link_counts)
        now = self.link.counts()
        return {k: v + self._link_counts.get(k, 0) for k, v in now.items()}

    def _inject(self, fault: Fault, t: float, log: LogWriter) -> None:
        face = self.face
        if fault.kind == "imu-stop":
            face.imu_stopped = True
        elif fault.kind == "imu-nan":
            face.imu_nan = True
        elif fault.kind == "link-drop":
            face.muted = True
        elif fault.kind == "rc-lost":
            face.rc_lost = True
        elif fault.kind == "position-lost":
            self.autopilot.position_valid = False
        elif fault.kind == "motor-fail":
            self.quad.set_motor_failure(fault.arg, 0.0)
        elif fault.kind in ("heartbeat-stop", "imu-range"):
            if self._outgoing is None:
                self._outgoing = OutgoingFaults(face.mav)
            if fault.kind == "heartbeat-stop":
                self._outgoing.drop_heartbeat = True
            else:
                self._outgoing.gyro_x_rad_s = IMU_RANGE_GYRO_RAD_S
        logger.warning("fault injected at t=%.3f s: %s", t, fault)
        log.event(Event(t, "fault", {"fault": fault.kind, "arg": fault.arg}))

    def _loop(self, log: LogWriter, summary: RunSummary, wall0: float) -> Status:
        cfg = self.config
        world, ap, face = self.world, self.autopilot, self.face
        quad, pilot, est = world.quad, world.pilot, world.estimator
        est_begin = False  # the estimator starts again: its first estimate at once
        snap = face.snapshot
        lockstep = cfg.clock == "lockstep"
        linked = not cfg.link.ideal
        duration = self.duration_s if self.duration_s is not None else math.inf
        joystick_pilot = cfg.pilot_input == "joystick"
        sticks: tuple[int, ...] | None = None
        rc = Every(cfg.rc_period_s)
        client_active = True
        sp_at_timeout = -1
        sp_seen, sp_seen_t = face.setpoints_arrived, -math.inf
        cmd_seen, cmd_seen_t = face.commands_received, -math.inf
        # (sim time, wall time) the clock keeps to while a client streams setpoints
        # outside OFFBOARD (module docstring); None: not keeping to the wall's.
        paced_from: tuple[float, float] | None = None
        motors: tuple[float, ...] = (0.0,) * self.profile.n_motors
        monotonic = time.monotonic
        stop = self.stop
        steps = 0

        if pilot is not None and cfg.auto_arm:
            ap.arm(0.0)
        # The pilot's start as a physics step: times since then are counted in
        # steps, so they are the same numbers whatever step arming fell on (an
        # in-process flight's, which starts at 0), not differences of two rounded
        # absolute times that miss a script's segment boundary by 1e-16 s.
        k_pilot0: int | None = None if cfg.pilot_from_arm else 0
        dt = quad.dt_s
        faults = sorted(cfg.faults, key=lambda f: f.t_s)
        pilot_duration = pilot.duration_s if pilot is not None else math.inf

        while not stop.is_set():
            t = quad.t_s
            # Since the pilot's start (arming, with pilot_from_arm); 0 before it.
            t_flight = 0.0 if k_pilot0 is None else (quad.steps - k_pilot0) * dt
            # With pilot_from_arm the flight's duration counts from arming, as the
            # pilot's timeline and the faults do; otherwise from the start.
            if t_flight >= duration - 1e-9:
                return "completed"
            # Fault times count from the pilot's start (arming, with --pilot-from-arm).
            while faults and k_pilot0 is not None and t_flight >= faults[0].t_s - 1e-9:
                self._inject(faults.pop(0), t, log)

            if (
                cfg.pilot_from_arm
                and self.config.duration_s is None
                and k_pilot0 is not None
                and t_flight >= pilot_duration + PILOT_END_GRACE_S - 1e-9
            ):
                return "completed"
            face.poll(t)
            # Armed at the start of this step (commands take effect only here in
            # lockstep): the flight's timeline starts now, whenever that was.
            if k_pilot0 is None and ap.armed:
                k_pilot0 = quad.steps
                t_flight = 0.0
                world.restart()
                self._make_link(t)
                est = world.estimator
                est_begin = True
                face.reset_setpoint_age()
                # The messages too: their schedules began when the client asked.
                self.streams.rephase(t)
                pilot = world.pilot
                rc = Every(cfg.rc_period_s, t)
                log.event(Event(t, "pilot_start", {"t_s": t}))
            st = quad.state
            euler = quat_to_euler_rad(st.q_wxyz)
            if pilot is not None and rc.due(t):
                sticks = world.sticks(t_flight, euler)
                if joystick_pilot and not face.rc_lost and isinstance(ap, Autopilot):
                    ap.on_manual_control(t, joystick_from_channels(sticks))
            sample = world.sense()
            snap.t_s = t
            snap.q_wxyz = st.q_wxyz
            snap.euler_rad = euler
            snap.pos_ned_m = st.pos_ned_m
            snap.vel_ned_m_s = st.vel_ned_m_s
            snap.sticks_us = sticks
            if est is None:
                snap.est_att_t_s = snap.est_pos_t_s = t
                snap.est_q_wxyz, snap.est_euler_rad = st.q_wxyz, euler
                snap.est_pos_ned_m, snap.est_vel_ned_m_s = st.pos_ned_m, st.vel_ned_m_s
            else:
                if est_begin:
                    est.begin(st)
                    est_begin = False
                    new_att = new_pos = True
                else:
                    new_att, new_pos = est.update(st)
                if new_att and est.attitude is not None:
                    a = est.attitude
                    snap.est_att_t_s = a.time_s
                    snap.est_q_wxyz = a.q_wxyz
                    snap.est_euler_rad = quat_to_euler_rad(a.q_wxyz)
                if new_pos and est.position is not None:
                    p = est.position
                    snap.est_pos_t_s = p.time_s
                    snap.est_pos_ned_m = p.position_ned_m
                    snap.est_vel_ned_m_s = p.velocity_ned_m_s
            if sample is not None:
                snap.imu_t_s = sample.time_s
                snap.gyro_frd_rad_s = sample.gyro_frd_rad_s
                snap.accel_frd_m_s2 = sample.accel_frd_m_s2
                log.imu(sample.time_s, sample.gyro_frd_rad_s)
            imu_sent = face.publish(t, imu_sample=sample is not None, wall_s=monotonic())

            if face.setpoints_arrived != sp_seen:
                sp_seen, sp_seen_t = face.setpoints_arrived, t
            if face.commands_received != cmd_seen:
                cmd_seen, cmd_seen_t = face.commands_received, t
            if not client_active and face.setpoints_arrived != sp_at_timeout:
                client_active = True  # setpoints resumed after a lockstep timeout
            if lockstep and imu_sent and client_active and ap.external_control:
                # One answer per sample the client got: through a modelled link,
                # each new sample the link delivered this step, sent when it arrived.
                want = face.setpoints_arrived + 1
                if linked:
                    want += len(face.samples_delivered) - 1
                    face.expect_answers(face.samples_delivered, min(face.samples_delivered_t))
                else:
                    face.expect_answers((), snap.imu_t_s)
                summary.lockstep_waits += 1
                deadline = monotonic() + cfg.lockstep_timeout_s
                while face.setpoints_arrived < want and not stop.is_set():
                    if face.leaving_external_control:
                        break  # a hand-back: applied at the next step, no answer coming
                    left = deadline - monotonic()
                    if left <= 0.0:
                        summary.lockstep_timeouts += 1
                        face.lockstep_timed_out()
                        client_active = False
                        sp_at_timeout = face.setpoints_arrived
                        logger.warning(
                            "lockstep: no setpoint within %.2f s at t=%.3f s; not waiting "
                            "until setpoints resume",
                            cfg.lockstep_timeout_s,
                            t,
                        )
                        break
                    if face.wait_readable(min(left, _KEEP_ALIVE_POLL_S)):
                        face.poll(t, defer_commands=True)
                    face.keep_alive(monotonic())
                face.expect_answers(())

            if sample is not None:
                motors = ap.update(
                    sample.time_s,
                    sample.gyro_frd_rad_s,
                    euler,
                    climb_rate_m_s=-st.vel_ned_m_s[2],
                    landed=st.landed,
                    crashed=st.crashed,
                    sticks_us=None if face.rc_lost or joystick_pilot else sticks,
                )
            if ap.events:
                for ev in ap.drain_events():
                    log.event(ev)

            log.append(
                [
                    t,
                    *st.rate_frd_rad_s,
                    *st.q_wxyz,
                    *st.pos_ned_m,
                    *st.vel_ned_m_s,
                    *st.motor_w_rad_s,
                    *motors,
                    ap.custom_mode,
                    1.0 if ap.armed else 0.0,
                ]
            )
            steps += 1
            summary.steps = steps
            if st.crashed:
                log.event(
                    Event(t, "flight_end", {"status": "crashed", "pos_ned_m": list(st.pos_ned_m)})
                )
                return "crashed"
            quad.step(motors)

            if not lockstep:
                # Pace simulation time to the wall clock; wake early for incoming data.
                while True:
                    ahead = quad.t_s - (monotonic() - wall0)
                    if ahead <= 0.0:
                        if -ahead > summary.max_lag_s:
                            summary.max_lag_s = -ahead
                        break
                    if face.wait_readable(ahead):
                        face.poll(quad.t_s)
            elif not ap.external_control and (
                quad.t_s - sp_seen_t <= _STREAMING_S or quad.t_s - cmd_seen_t <= _COMMANDING_S
            ):
                # A client streams setpoints the autopilot does not fly yet, or sets
                # it up: keep to the wall's clock, from where this began (module
                # docstring).
                if paced_from is None:
                    paced_from = (quad.t_s, monotonic())
                t_from, wall_from = paced_from
                while True:
                    ahead = (quad.t_s - t_from) - (monotonic() - wall_from)
                    if ahead <= 0.0 or stop.is_set():
                        break
                    if face.wait_readable(ahead):
                        face.poll(quad.t_s, defer_commands=True)
            else:
                paced_from = None
        return "stopped"
