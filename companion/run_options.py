"""Everything one run of the companion needs, validated before anything is opened."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from companion.config import MfcConfig, PidConfig
from companion.failsafe import FailsafeConfig
from companion.mission import FlightPlan
from companion.profile import VehicleProfile
from companion.rate_loop import LawAxes
from companion.reference import ReferenceScript

__all__ = ["RunOptions"]


@dataclass(frozen=True)
class RunOptions:
    """Everything a run needs, validated before anything is opened."""

    connect: str
    profile: VehicleProfile
    controller: MfcConfig | PidConfig
    profile_path: str = ""
    controller_path: str = ""
    output: Literal["actuator", "rates"] = "actuator"
    mode: Literal["rates", "angle", "altitude", "position"] = "rates"
    """What the sticks ask: body rates, or the outer loops on the autopilot's
    estimates (:mod:`companion.modes`)."""
    mission: FlightPlan | None = None
    """With ``mode="position"``: waypoints (or the lab's scripted setpoints) flown
    from where each engagement starts, instead of the sticks (:mod:`companion.mission`)."""
    engage: Literal["auto", "rc-switch", "none"] = "rc-switch"
    imu_source: Literal["auto", "highres_imu", "attitude"] = "auto"
    """"auto": the stack's (PX4 HIGHRES_IMU, ArduPilot ATTITUDE)."""
    loop_rate_hz: float = 250.0
    rc_rate_hz: float = 50.0
    engage_channel: int = 5
    rates_full_scale_deg_s: float = 360.0
    """With ``output="rates"``: the rate correction a full-scale law output makes.
    It sets the input gain the law sees through the autopilot's rate loop:
    measured on paper-acro with the PX4-like SITL, the profile's 1080 deg/s made
    the Tarot oscillate into the envelope failsafe, 360 flew every vehicle."""
    rates_lead_s: float = 0.03
    """With ``output="rates"`` (not pass-through): a feed-forward lead added to the
    setpoint, ``rates_lead_s`` times the derivative of the prefiltered pilot rate.
    The autopilot's closed rate loop lags its setpoint (about 70 ms for the SITL's
    ArduPilot personality); the law's own feed-forward ``y_r''/alpha``, with alpha
    identified on that closed loop, is only about 8 ms of it. The lead is not
    taught to the F estimate as applied: taught, it drags the identified alpha
    down and the law's feedback rings. Measured: docs/research/ardupilot.md."""
    rates_passthrough: bool = False
    """With ``output="rates"``: send the pilot's rates unchanged (the baseline the
    MFC-on-top is compared with); the law still runs and is logged."""
    rates_law_axes: LawAxes | None = None
    """With ``output="rates"``: per axis (roll, pitch, yaw), whether the law's
    correction is added to the pilot's rate. On an axis without it the setpoint
    is the pilot's rate and the lead, and the law there is taught that nothing
    of its output was applied. None (``--rates-law-axes auto``): chosen at
    start-up from the autopilot's rate gains (:mod:`companion.rate_loop`), all
    three until then and where the stack has no rule."""
    log_dir: Path | None = None
    mqtt_url: str | None = None
    live: tuple[str, int] | None = None
    """Serve the control log's topics live here, ``(host, port)`` (:mod:`companion.live`)."""
    signing_key: Path | None = None
    duration_s: float | None = None
    reference: ReferenceScript | None = None
    """Scripted rates (and maybe thrust) from engagement on, instead of the sticks."""
    heartbeat_timeout_s: float = 10.0
    arm_timeout_s: float = 60.0
    """With ``engage="auto"``: how long to keep trying the engage mode and the
    arming while the stack refuses them or its pre-arm checks fail (ArduCopter
    needs a few seconds after boot for an altitude estimate, 40-50 s for a
    position); 0: one try each."""
    fly_check_event: tuple[str, str] | None = None
    """The controller file's fly check (:mod:`companion.fly_check`) as an event
    ``(kind, detail)`` recorded at the start: ``fly_check_passed``, or
    ``fly_check_skipped`` (a warning too); None for a shipped file."""
    autopilot_sysid: int | None = None
    autopilot_compid: int | None = None
    """Pin the autopilot; ``None``: learn it from its first HEARTBEAT."""
    failsafe: FailsafeConfig = field(default_factory=FailsafeConfig)
