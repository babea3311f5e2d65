"""The flight core alone: no event loop, no socket, the clock the test's.

Each test feeds :class:`companion.core.FlightCore` what would arrive and reads
what it asked of its shell (:class:`sitl.lab.inprocess.LabShell` keeps it), as
``companion run`` and the lab's flights both do.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import DEFAULT_CONTROLLER, load_controller
from companion.core import FlightCore
from companion.flight_modes import FLIGHT_MODES
from companion.options import FLIGHT_MODE_NAMES
from companion.profile import load_profile
from companion.run_options import RunOptions
from companion.stacks import PX4
from sitl.lab.inprocess import LabShell, engaged_core, rc_frame

ROOT = Path(__file__).resolve().parents[2]
PROFILE = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
CONTROLLER = load_controller(DEFAULT_CONTROLLER)
CENTRED = (1500, 1500, 1500, 1500, 1000)  # sticks centred, half throttle, ch5 low


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def options(**kw: object) -> RunOptions:
    kw.setdefault("engage", "rc-switch")
    return RunOptions(connect="test", profile=PROFILE, controller=CONTROLLER, **kw)  # type: ignore[arg-type]


def test_the_command_line_names_every_flight_mode_and_no_other() -> None:
    assert tuple(FLIGHT_MODES) == FLIGHT_MODE_NAMES


def test_engaged_it_sends_one_command_per_sample_flown_and_drops_a_late_one() -> None:
    shell, clock = LabShell(), Clock()
    core = engaged_core(options(output="actuator"), shell, clock)
    core.on_rc(rc_frame(CENTRED), clock.t)
    sent = []
    for k in range(5):
        shell.controls = None
        core.on_imu(10.0 + 0.004 * k, (0.0, 0.0, 0.0), clock.t + 0.004 * k)
        sent.append(shell.controls)
    assert all(c is not None and len(c) == 8 for c in sent)
    shell.controls = None
    core.on_imu(10.008, (0.0, 0.0, 0.0), clock.t + 0.02)  # a late duplicate
    assert shell.controls is None
    assert core.counters()["imu_duplicate_or_late"] == 1
    assert core.output.n_commands == 5


def test_the_switch_engages_through_the_shell_and_hands_back_when_low() -> None:
    asked: list[str] = []

    class Shell(LabShell):
        def engage(self) -> None:
            asked.append("engage")

        def hand_back(self, reason: str, *, was_commanding: bool) -> None:
            asked.append(f"hand back: {reason} ({was_commanding})")

    shell, clock = Shell(), Clock()
    core = FlightCore(options(), shell, clock)
    core.stack, core.started_up = PX4, True
    core.on_rc(rc_frame((*CENTRED[:4], 2000)), clock.t)  # high at start: nothing
    assert asked == [] and shell.events[-1][0] == "rc_switch_high_at_start"
    core.on_rc(rc_frame(CENTRED), clock.t)
    core.on_rc(rc_frame((*CENTRED[:4], 2000)), clock.t)
    assert asked == ["engage"]
    core.begin_commanding()
    core.on_rc(rc_frame(CENTRED), clock.t)
    assert asked[-1] == "hand back: pilot switched back (True)"
    assert not core.commanding


def test_a_failsafe_stops_the_commands_in_the_call_that_finds_it() -> None:
    shell, clock = LabShell(), Clock()
    core = engaged_core(options(output="actuator"), shell, clock)
    core.on_rc(rc_frame(CENTRED), clock.t)
    core.on_imu(10.0, (0.0, 0.0, 0.0), clock.t)
    nan = float("nan")
    for k in range(1, 40):  # a gyro that reads NaN for longer than invalid_imu_s
        shell.controls = None
        core.on_imu(10.0 + 0.004 * k, (nan, nan, nan), clock.t + 0.004 * k)
        if shell.failsafes:
            break
    assert shell.failsafes and shell.failsafes[0][0] == "failsafe_invalid_imu"
    assert not core.commanding and not core.engaged
    shell.controls = None
    core.on_imu(11.0, (0.0, 0.0, 0.0), clock.t + 1.0)
    assert shell.controls is None  # nothing after it
    core.failsafe("failsafe_envelope", "a second one")  # one at a time
    assert len(shell.failsafes) == 1


def test_the_pilot_is_stale_by_the_clock_it_is_given() -> None:
    shell, clock = LabShell(), Clock()
    core = FlightCore(options(), shell, clock)
    core.on_rc(rc_frame(CENTRED), 5.0)
    assert core.pilot.fresh(5.4)
    assert not core.pilot.fresh(5.6)  # rc_timeout_s 0.5
    assert core.conditions(5.4, rc_failsafe=False).rc_valid


@pytest.mark.parametrize("name", FLIGHT_MODE_NAMES)
def test_each_flight_mode_says_what_it_flies_on(name: str) -> None:
    mode = FLIGHT_MODES[name]
    assert mode.needs_attitude == (name != "rates")
    assert mode.needs_position == (name in ("altitude", "position"))
    assert mode.flies_missions == (name == "position")
    core = FlightCore(options(mode=name), LabShell(), Clock())
    assert core.needs_attitude == mode.needs_attitude
    why = core.not_ready_to_engage(0.0)
    assert (why is None) == (name == "rates")


def test_each_row_carries_the_model_the_law_flies() -> None:
    """alpha, the lag and the delay, per axis, as the law has them at that sample."""
    from companion.records import columns

    shell, clock = LabShell(), Clock()
    core = engaged_core(options(output="actuator"), shell, clock)
    rows: list[list[float]] = []
    core.output.log_append = rows.append
    core.on_rc(rc_frame(CENTRED), clock.t)
    for k in range(3):
        core.on_imu(10.0 + 0.004 * k, (0.0, 0.0, 0.0), clock.t + 0.004 * k)
    names = columns(PROFILE.n_motors)
    assert all(len(r) == len(names) for r in rows) and len(rows) == 3
    alpha, lag, delay = core.controller.identified()
    for i, axis in enumerate(("roll", "pitch", "yaw")):
        assert rows[-1][names.index(f"alpha_{axis}")] == alpha[i] > 0.0
        assert rows[-1][names.index(f"lag_{axis}_s")] == lag[i] >= 0.0
        assert rows[-1][names.index(f"delay_{axis}_s")] == delay[i] >= 0.0


def _commands(nan_between: bool) -> list[tuple[float, ...]]:
    """The commands an engaged core sends for 60 samples of a varying rate, with or
    without a NaN sample stamped 1 ms after every valid one."""
    shell, clock = LabShell(), Clock()
    core = engaged_core(options(output="actuator"), shell, clock)
    core.on_rc(rc_frame((1600, 1450, 1500, 1500, 1000)), clock.t)
    sent = []
    for k in range(60):
        t = 10.0 + 0.004 * k
        shell.controls = None
        core.on_imu(t, (0.3 * (k % 7) / 7, -0.1, 0.05), clock.t + 0.004 * k)
        assert shell.controls is not None
        sent.append(tuple(shell.controls))
        if nan_between:
            core.on_imu(t + 0.001, (float("nan"), 0.0, 0.0), clock.t + 0.004 * k + 0.001)
    return sent


def test_an_invalid_sample_between_two_valid_ones_changes_no_command_of_theirs() -> None:
    """The law holds on a NaN sample, so it is not flown: the next valid sample's
    step counts from the last valid one, not from the NaN's stamp (found by
    ``scripts/fuzz.py``: NaN samples between real ones cost 1.23-1.39x roll MAE)."""
    assert _commands(nan_between=True) == _commands(nan_between=False)


def test_the_law_is_given_the_time_since_the_last_sample_it_flew() -> None:
    """The steps the law is given, around invalid samples: their time is carried
    to the next valid sample, except to a priming one (step 0), which stays 0."""
    from companion.step import SampleStep

    class Law:
        def __init__(self) -> None:
            self.steps: list[float] = []

        def update(self, dt: float, *_: object) -> None:
            self.steps.append(dt)

    law = Law()
    step = SampleStep(law, PROFILE)  # type: ignore[arg-type]
    nan, ok = (float("nan"), 0.0, 0.0), (0.1, 0.0, 0.0)
    for dt, gyro in ((0.0, ok), (0.004, ok), (0.001, nan), (0.003, ok), (0.004, nan), (0.0, ok)):
        step.sample(dt, gyro, (0.0, 0.0, 0.0), 0.5)
    assert law.steps == [0.0, 0.004, 0.001, 0.004, 0.004, 0.0]
    assert step.held_dt_s == 0.0
