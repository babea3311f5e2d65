"""The simulated world both loops step (sitl/world.py)."""

from __future__ import annotations

from pathlib import Path

from companion.profile import load_profile
from sitl.pilot import make_pilot
from sitl.wind import WindConfig
from sitl.world import Every, World, WorldSpec, flight_streams

ROOT = Path(__file__).resolve().parents[2]


def _spec(**kw: object) -> WorldSpec:
    profile = load_profile(ROOT / "vehicle_profiles/f450.yaml")
    base = dict(
        dt_s=0.001,
        test_stand=False,
        imu_model=profile.physics.imu,
        wind=WindConfig(gust_sigma_m_s=1.0),
        pilot="paper-acro",
        hover_throttle=0.4,
    )
    base.update(kw)
    return WorldSpec(**base)  # type: ignore[arg-type]


def test_a_schedule_is_due_at_its_start_and_once_per_period() -> None:
    every = Every(0.02, start_s=1.0)
    assert not every.due(0.999)
    assert every.due(1.0)
    assert not every.due(1.0)
    assert not every.due(1.019)
    assert every.due(1.02)


def test_a_50hz_schedule_falls_on_its_physics_step_for_a_whole_flight() -> None:
    # The sum of 0.02 s periods rounds past k * 1 ms by more than 1e-12 s after 42 s:
    # a schedule due only 1e-12 s early took those frames one step late.
    every, dt = Every(0.02), 0.001
    due = [k for k in range(120_000) if every.due(k * dt)]
    assert due == list(range(0, 120_000, 20))


def test_a_world_begun_again_draws_what_it_drew_at_the_start() -> None:
    profile = load_profile(ROOT / "vehicle_profiles/f450.yaml")
    world = World(profile, _spec(), seed=7)

    def fly(n: int) -> list[tuple[int, ...] | tuple[float, ...]]:
        out: list[tuple[int, ...] | tuple[float, ...]] = []
        for k in range(n):
            if k % 20 == 0:
                out.append(world.sticks(k * 0.001))
            sample = world.sense()
            if sample is not None:
                out.append(sample.gyro_frd_rad_s)
            world.quad.step((0.0,) * profile.n_motors)
        return out

    first = fly(200)
    world.restart()
    # The physics went on (the vehicle sat on the ground, motors off): the IMU's
    # noise, the wind and the pilot are drawn from the start of their streams again.
    assert fly(200) == first


def test_each_source_has_its_own_stream_of_the_seed() -> None:
    a, b = flight_streams(3), flight_streams(3)
    assert a.keys() == {"plant", "imu", "wind", "pilot"}
    assert a["pilot"].random() == b["pilot"].random()
    assert a["imu"].random() != a["wind"].random()


def test_a_given_pilot_flies_in_place_of_the_named_one() -> None:
    profile = load_profile(ROOT / "vehicle_profiles/f450.yaml")
    mine = make_pilot("hover", rng=flight_streams(1)["pilot"], free_flight=True)
    world = World(profile, _spec(), seed=1, pilot=mine)
    world.restart()
    assert world.pilot is mine
