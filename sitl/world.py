"""One flight's simulated world: the vehicle's physics, its IMU, the air, the
pilot and the autopilot's estimator, each drawing from its own stream of the
flight's seed.

Two loops step a world, and differ only in who flies it: the SITL's
(:mod:`sitl.runner`: an autopilot personality behind MAVLink, a companion in
another process) and the lab's (:mod:`sitl.lab.simulate`: the companion's
flight core called in process). Each physics step they ask the world the same
things in the same order: the pilot's sticks when an RC frame is due
(:meth:`World.sticks`), the IMU's sample (:meth:`World.sense`), then they step
the physics with the motors their autopilot made (``world.quad.step``). So a
seed gives the same wind, noise and pilot both ways, and the same flight.

Seeding: one :class:`numpy.random.SeedSequence` from the flight's seed is
split into children for the plant, the IMU, the wind and the pilot
(:func:`flight_streams`, children 0-3), so changing one source never shifts
another's numbers; the estimator has a sequence of its own
(:func:`~sitl.estimator_model.estimator_seed_sequence`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.profile import ImuModel, VehicleProfile
from sitl.estimator_model import EstimatorModel, EstimatorSpec, estimator_seed_sequence
from sitl.frames import quat_to_euler_rad
from sitl.imu import Imu, ImuSample
from sitl.physics import Quadrotor
from sitl.pilot import Pilot, PilotView, make_pilot
from sitl.wind import Wind, WindConfig

__all__ = ["Every", "World", "flight_streams"]

_STREAMS = ("plant", "imu", "wind", "pilot")

_DUE_SLACK_S = 1e-9
"""A schedule's time is due this much early: its sum of periods and the physics'
``k dt`` round differently, and one step is 1e6 times longer."""


def flight_streams(seed: int) -> dict[str, np.random.Generator]:
    """Independent generators for each random source of a flight."""
    children = np.random.SeedSequence(seed).spawn(len(_STREAMS))
    return {n: np.random.default_rng(s) for n, s in zip(_STREAMS, children, strict=True)}


class Every:
    """A periodic schedule in simulation time: due at its start, then once per period."""

    def __init__(self, period_s: float, start_s: float = 0.0) -> None:
        self.period_s = period_s
        self.next_s = start_s

    def due(self, t_s: float) -> bool:
        """Whether it is due at ``t_s``; if so, the next time is one period on."""
        if t_s < self.next_s - _DUE_SLACK_S:
            return False
        self.next_s += self.period_s
        return True


@dataclass(frozen=True)
class WorldSpec:
    """What a world is made of, besides the vehicle and the seed."""

    dt_s: float
    test_stand: bool
    imu_model: ImuModel
    wind: WindConfig | None
    pilot: str | None
    """The pilot's name (:func:`~sitl.pilot.make_pilot`), or None: no pilot."""
    hover_throttle: float
    """The throttle the pilot takes for a hover, in its autopilot's units."""
    estimator: EstimatorSpec | None = None
    """The autopilot's estimator, or None: it has none (the truth is streamed)."""


class World:
    """The vehicle, its IMU, the air, the pilot and the estimator of one flight."""

    def __init__(
        self,
        profile: VehicleProfile,
        spec: WorldSpec,
        seed: int,
        *,
        pilot: Pilot | None = None,
    ) -> None:
        """``pilot`` flies in place of the one ``spec`` names (which then only names it)."""
        self.spec = spec
        self.seed = seed
        self.quad = Quadrotor(
            profile, rng=flight_streams(seed)["plant"], dt_s=spec.dt_s, test_stand=spec.test_stand
        )
        self._given_pilot = pilot
        self.imu: Imu
        self.pilot: Pilot | None
        self.estimator: EstimatorModel | None
        self.restart()

    def restart(self) -> None:
        """The air, the IMU, the pilot and the estimator begin again from their
        streams of the seed, the physics as it is: at the start, and again at
        the pilot's start in a SITL flight that waits for arming, so a flight
        does not depend on how long the vehicle sat before it."""
        spec = self.spec
        rngs = flight_streams(self.seed)
        self.quad.set_wind(None if spec.wind is None else Wind(spec.wind, rng=rngs["wind"]))
        self.imu = Imu(spec.imu_model, rng=rngs["imu"], dt_s=spec.dt_s)
        if self._given_pilot is not None:
            self.pilot = self._given_pilot
        elif spec.pilot:
            self.pilot = make_pilot(spec.pilot, rng=rngs["pilot"], free_flight=not spec.test_stand)
        else:
            self.pilot = None
        self.estimator = None
        if spec.estimator is not None:
            self.estimator = EstimatorModel(
                spec.estimator,
                rng=np.random.default_rng(estimator_seed_sequence(self.seed)),
                dt_s=spec.dt_s,
                imu_rate_hz=min(spec.imu_model.rate_hz, 1.0 / spec.dt_s),
            )

    def pilot_view(
        self, t_s: float, euler_rad: tuple[float, float, float] | None = None
    ) -> PilotView:
        """What the pilot sees of the vehicle now; ``t_s`` on the pilot's timeline."""
        st = self.quad.state
        roll, pitch, yaw = quat_to_euler_rad(st.q_wxyz) if euler_rad is None else euler_rad
        return PilotView(
            t_s=t_s,
            roll_rad=roll,
            pitch_rad=pitch,
            yaw_rad=yaw,
            rate_frd_rad_s=st.rate_frd_rad_s,
            altitude_m=-st.pos_ned_m[2],
            climb_rate_m_s=-st.vel_ned_m_s[2],
            hover_throttle=self.spec.hover_throttle,
        )

    def sticks(
        self, t_s: float, euler_rad: tuple[float, float, float] | None = None
    ) -> tuple[int, ...]:
        """The pilot's RC channels now (there must be a pilot)."""
        assert self.pilot is not None
        return self.pilot.sticks(self.pilot_view(t_s, euler_rad)).channels()

    def sense(self) -> ImuSample | None:
        """The IMU's sample of the vehicle now, if one is due."""
        q = self.quad
        return self.imu.update(q.t_s, q.rate_frd_rad_s, q.specific_force_frd_m_s2)
