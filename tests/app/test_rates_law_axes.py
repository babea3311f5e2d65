"""``companion run --output rates --rates-law-axes``: the law corrects only the axes named.

On the others the setpoint is the pilot's rate and the lead, and the law there is
taught that nothing of its output went out; replay reproduces such a flight. With
``auto`` (the default) the axes are chosen at start-up from PX4's rate gains
(companion.rate_loop), and the log's metadata says which.
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
    return (await _flight(start, log_dir, **opts))[0]


async def _flight(
    start: Start, log_dir: Path, **opts: object
) -> tuple[list[tuple[float, ...]], Flight]:
    """The setpoints sent while the vehicle turns under centred sticks, and the flight."""
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
    return sent, f


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


STIFF_PX4 = {"MC_ROLLRATE_K": 3.0, "MC_ROLLRATE_P": 0.15, "MC_PITCHRATE_K": 1.0,
             "MC_PITCHRATE_P": 0.3}  # fmt: skip
"""PX4's roll rate loop at three times its default gain (K), pitch's at twice (P)."""
DEFAULT_PX4 = {"MC_ROLLRATE_K": 1.0, "MC_ROLLRATE_P": 0.15, "MC_PITCHRATE_K": 1.0,
               "MC_PITCHRATE_P": 0.15}  # fmt: skip


async def test_auto_leaves_a_stiff_loops_roll_and_pitch_to_the_pilot_and_replays(
    start: Start, tmp_path: Path
) -> None:
    sent, f = await _flight(start, tmp_path / "auto", params=STIFF_PX4)
    yaw = np.array(sent)
    assert len(yaw) > 50
    assert (yaw[:, :2] == 0.0).all()  # centred sticks: no rate, no lead
    assert np.abs(yaw[:, 2]).max() > 0.05
    (said,) = f.details("rates_law_axes")
    assert said.startswith("MC_ROLLRATE_K 3, MC_ROLLRATE_P 0.15, MC_PITCHRATE_K 1, "
                           "MC_PITCHRATE_P 0.3: 3x / 2x the default gain"), said  # fmt: skip
    assert said.endswith("the law corrects yaw; roll and pitch: the pilot's rate and the lead")
    cols, meta = read_control_log(tmp_path / "auto" / "control.mcap")
    assert meta["rates_law_axes"] == "yaw"  # learnt at start-up, over the first "auto"
    diffs = compare(cols, replay(cols, RATES, PROFILE, meta=meta))
    assert max(diffs.values()) <= REPLAY_TOLERANCE, diffs
    # Without the record of the choice, replay refuses rather than guess.
    with pytest.raises(ValueError, match=r"companion\.learnt"):
        replay(cols, RATES, PROFILE, meta={**meta, "rates_law_axes": "auto"})


UNANSWERED = {**STIFF_PX4, "MC_PITCHRATE_P": None}
NOT_POSITIVE = {**STIFF_PX4, "MC_ROLLRATE_P": 0.0}


@pytest.mark.parametrize(
    ("params", "asked", "kind"),
    [
        (DEFAULT_PX4, None, "rates_law_axes"),
        (UNANSWERED, None, "rates_law_axes_assumed"),  # one not answered: all three
        (NOT_POSITIVE, None, "rates_law_axes_assumed"),
        (STIFF_PX4, (True, True, True), None),  # asked: not chosen, nothing read
    ],
)
async def test_every_axis_where_the_loop_is_not_stiff_unread_or_all_are_asked(
    start: Start,
    tmp_path: Path,
    params: dict[str, float] | None,
    asked: tuple[bool, bool, bool] | None,
    kind: str | None,
) -> None:
    opts = {} if asked is None else {"rates_law_axes": asked}
    sent, f = await _flight(start, tmp_path, params=params, **opts)
    every = np.array(sent)
    assert (np.abs(every).max(axis=0) > 0.05).all()
    assert f.kinds().count("rates_law_axes") == (kind is not None)
    if kind is not None:
        assert kind in f.kinds()
        (said,) = f.details("rates_law_axes")
        assert said.endswith(": the law corrects roll, pitch, yaw"), said
    if kind == "rates_law_axes":  # read, and judged: not a fallback
        assert "rates_law_axes_assumed" not in f.kinds()
        assert said.startswith("MC_ROLLRATE_K 1, MC_ROLLRATE_P 0.15, MC_PITCHRATE_K 1, "
                               "MC_PITCHRATE_P 0.15: 1x / 1x the default gain"), said  # fmt: skip
    elif kind is not None:
        assert said.startswith("MC_PITCHRATE_P not read" if params is UNANSWERED
                               else "MC_ROLLRATE_P not read"), said  # fmt: skip
    _, meta = read_control_log(tmp_path / "control.mcap")
    assert meta["rates_law_axes"] == "roll,pitch,yaw"


@pytest.mark.parametrize(
    ("value", "words"),
    [
        ("roll,spin", ("--rates-law-axes", "expected a comma-separated set", "'roll,spin'")),
        ("yaw,yaw", ("--rates-law-axes", "each once")),
        ("", ("--rates-law-axes", "or 'auto'")),
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
