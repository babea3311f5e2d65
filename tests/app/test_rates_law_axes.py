"""``companion run --output rates --rates-law-axes``: the law corrects only the axes named.

On the others the setpoint is the pilot's rate and the lead, and the law there is
taught that nothing of its output went out; replay reproduces such a flight.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.cli import REPLAY_TOLERANCE
from companion.config import RATES_CONTROLLER, load_controller
from companion.records import read_control_log
from companion.replay import compare, replay
from tests.app.fakes import CMD_ARM, PX4_OFFBOARD, settle
from tests.app.flight import PROFILE, Flight, Start, streams_requested
from tests.test_bad_input import companion, refused

RATES = load_controller(RATES_CONTROLLER)
SPIN = (0.6, -0.4, 0.5)  # rad/s: the vehicle turns while the sticks are centred


async def _flown(start: Start, log_dir: Path, **opts: object) -> list[tuple[float, ...]]:
    """The setpoints sent while the vehicle turns under centred sticks."""
    f: Flight = await start(
        engage="auto", output="rates", controller=RATES, log_dir=log_dir, **opts
    )
    await streams_requested(f)
    f.fake.extended_sys_state(2)  # MAV_LANDED_STATE_IN_AIR
    f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), what="ARM")
    f.fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(lambda: f.companion.engaged, what="engaged")
    n0 = len(f.fake.of_type("SET_ATTITUDE_TARGET"))
    for _ in range(150):
        f.imu(SPIN)
        await settle(2)
    sent = [
        (m.body_roll_rate, m.body_pitch_rate, m.body_yaw_rate)
        for m in f.fake.of_type("SET_ATTITUDE_TARGET")[n0:]
    ]
    f.companion._stop.set()
    await f.finish()
    return sent


async def test_yaw_alone_sends_the_pilots_roll_and_pitch_and_replays(
    start: Start, tmp_path: Path
) -> None:
    every = np.array(await _flown(start, tmp_path / "all"))
    yaw = np.array(await _flown(start, tmp_path / "yaw", rates_law_axes=(False, False, True)))
    assert len(every) > 50 and len(yaw) > 50
    # The law fights the turn on every axis it is given, and only there.
    assert np.abs(every[:, :2]).max() > 0.05
    assert (yaw[:, :2] == 0.0).all()  # centred sticks: no rate, no lead
    assert np.abs(yaw[:, 2]).max() > 0.05

    cols, meta = read_control_log(tmp_path / "yaw" / "control.mcap")
    assert meta["rates_law_axes"] == "yaw"
    diffs = compare(cols, replay(cols, RATES, PROFILE, meta=meta))
    assert max(diffs.values()) <= REPLAY_TOLERANCE, diffs
    # Replayed as if the law's roll and pitch had gone out, the flight is not this one.
    every_axis = {**meta, "rates_law_axes": "roll,pitch,yaw"}
    diffs = compare(cols, replay(cols, RATES, PROFILE, meta=every_axis))
    assert max(diffs.values()) > 1e3 * REPLAY_TOLERANCE, diffs


@pytest.mark.parametrize(
    ("value", "words"),
    [
        ("roll,spin", ("--rates-law-axes", "expected a comma-separated set", "'roll,spin'")),
        ("yaw,yaw", ("--rates-law-axes", "each once")),
        ("", ("--rates-law-axes",)),
    ],
)
def test_run_refuses_an_axis_it_does_not_know(value: str, words: tuple[str, ...]) -> None:
    res = companion(
        "run", "--connect", "udpout:127.0.0.1:9", "--output", "rates", "--rates-law-axes", value
    )
    refused(res, *words)


def test_run_refuses_law_axes_without_rates_output() -> None:
    res = companion("run", "--connect", "udpout:127.0.0.1:9", "--rates-law-axes", "yaw")
    refused(res, "--rates-law-axes: needs --output rates")
