"""Rates output to ArduCopter, which shapes body-rate setpoints (companion.control.shaping).

Found on the real ArduCopter 4.5.6 SITL: unaware of the shaping, the law fought it
and the yaw limit-cycled; the companion now reads ATC_RATE_FF_ENAB and
ATC_ACCEL_{R,P,Y}_MAX, flies the pilot's rates so shaped, keeps its setpoints
within them and within what they bring in over a short horizon of the shaped
reference, and is taught what it sent. Replay reproduces such a flight.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from companion.cli import REPLAY_TOLERANCE
from companion.config import RATES_CONTROLLER, load_controller
from companion.control import AXES
from companion.control.shaping import CORRECTION_HORIZON_S
from companion.records import read_control_log
from companion.replay import compare, replay
from tests.app.fakes import APM_ALT_HOLD, APM_GUIDED_NOGPS, CMD_ARM, settle
from tests.app.flight import ARDUPILOT, MSG_ATTITUDE, PROFILE, Flight, Start, streams_requested

RATES = load_controller(RATES_CONTROLLER)

SHAPING = {
    "GUID_OPTIONS": 8.0,
    "ATC_RATE_FF_ENAB": 1.0,
    "ATC_ACCEL_R_MAX": 110000.0,
    "ATC_ACCEL_P_MAX": 110000.0,
    "ATC_ACCEL_Y_MAX": 27000.0,
}


async def _engaged(start: Start, params: dict[str, float | None], **opts: Any) -> Flight:
    f = await start(autopilot=ARDUPILOT, custom_mode=APM_ALT_HOLD, engage="auto",
                    output="rates", params=params, controller=RATES, **opts)  # fmt: skip
    # Unreadable parameters take their read timeouts (3 tries of 0.5 s) first.
    await f.fake.wait_until(lambda: f.companion.core.modes.imu_rate_hz is not None, 5.0)
    await streams_requested(f, MSG_ATTITUDE)
    f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=f.att, what="ARM")
    f.fake.set_state(APM_GUIDED_NOGPS, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=f.att, what="engaged")
    return f


async def test_the_setpoints_respect_ardupilots_shaping_and_replay_reproduces_them(
    start: Start, tmp_path: Path
) -> None:
    f = await _engaged(start, SHAPING, log_dir=tmp_path)
    (said,) = f.details("rate_shaping")
    assert "1100/1100/270 deg/s^2" in said
    n0 = len(f.fake.setpoints())
    # Full stick right and nose right at once: 720 and 360 deg/s asked.
    for k in range(120):
        f.fake.rc(1000, sticks=(2000, 1500, 1500, 2000))
        f.att((0.002 * k, 0.0, 0.001 * k))
        await settle(2)
    sent = f.fake.setpoints()[n0:]
    roll = [m.body_roll_rate for m in sent]
    yaw = [m.body_yaw_rate for m in sent]
    dt = 0.003  # the fake's ATTITUDE period
    steps_roll = np.abs(np.diff(roll))
    steps_yaw = np.abs(np.diff(yaw))
    assert steps_roll.max() <= math.radians(1100.0) * dt * 1.0001 + 1e-6  # float32 on the wire
    assert steps_yaw.max() <= math.radians(270.0) * dt * 1.0001 + 1e-6
    assert max(roll) > math.radians(100.0)  # it does go
    f.companion._stop.set()
    await f.finish()

    cols, meta = read_control_log(tmp_path / "control.mcap")
    engaged = cols["engaged"] > 0.5
    law = cols["law_ref_roll_rad_s"][engaged]
    pilot = cols["ref_roll_rad_s"][engaged]
    assert np.isfinite(law).all()
    assert (law < pilot - 1e-9).any()  # the law flew the shaped reference, below the stick's
    out = replay(cols, RATES, PROFILE, meta=meta)
    diffs = compare(cols, out)
    # As `companion replay` requires (the laws' dt is the stamps' difference there, and
    # rounded to whole us live: a few 1e-11 apart); untaught, it would be order 1 apart.
    assert max(diffs.values()) <= REPLAY_TOLERANCE, diffs


async def test_the_correction_stays_within_what_the_slew_brings_in_over_the_horizon(
    start: Start, tmp_path: Path
) -> None:
    """Sticks centred while the vehicle turns at 1 rad/s on every axis: the law asks
    for a full correction against it, and the setpoint goes only as far as the
    shaped reference plus ``a_max`` times the horizon (ArduCopter's 270 deg/s^2 on
    yaw: 13.5 deg/s; unheld, it slews on to the law's full 1.2 rad/s and more)."""
    f = await _engaged(start, SHAPING, log_dir=tmp_path)
    for _ in range(150):
        f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
        f.att((1.0, 1.0, 1.0))
        await settle(2)
    f.companion._stop.set()
    await f.finish()
    cols, _ = read_control_log(tmp_path / "control.mcap")
    engaged = cols["engaged"] > 0.5
    for a, accel in zip(AXES, (1100.0, 1100.0, 270.0), strict=True):
        sent = cols[f"sent_{a}_rad_s"][engaged]
        law = cols[f"law_ref_{a}_rad_s"][engaged]
        ok = np.isfinite(sent)
        assert ok.sum() > 100
        reach = math.radians(accel) * CORRECTION_HORIZON_S
        gap = np.abs(sent[ok] - law[ok])
        assert gap.max() <= reach * 1.0001 + 1e-6, (a, gap.max(), reach)
        assert gap.max() >= 0.99 * reach, (a, gap.max(), reach)  # the law did ask for more


async def test_shaping_parameters_that_cannot_be_read_are_assumed_and_said(
    start: Start,
) -> None:
    unanswered: dict[str, float | None] = {
        "GUID_OPTIONS": 8.0,
        **dict.fromkeys(
            ("ATC_RATE_FF_ENAB", "ATC_ACCEL_R_MAX", "ATC_ACCEL_P_MAX", "ATC_ACCEL_Y_MAX")
        ),
    }
    f = await _engaged(start, unanswered)
    (said,) = f.details("rate_shaping_assumed")
    assert "ATC_RATE_FF_ENAB" in said and "defaults assumed" in said
    assert f.companion.core.step.shaper is not None
    assert f.companion.core.step.shaper.accel_max_rad_s2 == tuple(
        math.radians(a) for a in (1100.0, 1100.0, 270.0)
    )


async def test_shaping_switched_off_is_not_modelled(start: Start) -> None:
    f = await _engaged(start, {**SHAPING, "ATC_RATE_FF_ENAB": 0.0})
    assert f.companion.core.step.shaper is None
    assert f.details("rate_shaping") == ["ATC_RATE_FF_ENAB = 0: rate setpoints not shaped"]
