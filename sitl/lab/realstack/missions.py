"""A mission flown by the companion and by the stack's own mission, on the real stacks.

One mission file (:data:`SQUARE_MISSION`, ``companion.mission``'s format: a 10 m
square from where the vehicle is, 3 m/s, one leg climbing 3 m) is flown twice from
the stack's hold (PX4 AUTO.LOITER, ArduCopter ALT_HOLD at mid-stick):

* by ``companion run --mode position --mission FILE``, engaged by the pilot's
  switch, the sticks centred (:func:`fly_companion_mission`); its waypoints are
  from where it engaged (its ``mission_started`` event);
* by the stack (:func:`fly_stack_mission`): the same waypoints, from where the
  vehicle is, turned into latitude and longitude about its GLOBAL_POSITION_INT
  (a local tangent plane: at 10 m the flat earth is exact to a millimetre) at
  heights above home (``MAV_FRAME_GLOBAL_RELATIVE_ALT_INT``), uploaded with the
  mission protocol and flown in the stack's mission mode (PX4 AUTO.MISSION;
  ArduCopter AUTO, which in the air needs nothing of the throttle stick and only
  refuses an armed vehicle on the ground without a take-off item), switched to
  from the ground station. Its leg speed is the mission's: PX4's ``MPC_XY_CRUISE``
  and ArduCopter's ``WPNAV_SPEED`` are set for the flight and restored after;
  everything else is the stack's default (PX4 turns to face each waypoint,
  ArduCopter too; the companion keeps its heading).

Each flight ends once its flyer says it has reached the last waypoint (the
companion's ``mission_waypoint`` event; the stack's MISSION_ITEM_REACHED), the
vehicle is there (:data:`ARRIVED_M`) and has slowed down, or after a bound.
:func:`mission_figures` measures both the same way, from what the ground station
received (ATTITUDE, LOCAL_POSITION_NED), from the engagement to the arrival:

* the path error: the horizontal distance to the straight legs (the polyline from
  the start through the waypoints, seen from above), RMS and largest;
* the altitude error: the height against the legs' at the closest point, RMS and
  largest;
* the largest tilt, the largest and mean horizontal speed;
* the time to complete: from the switch (or the mode asked for) until the vehicle
  has passed every waypoint in order (within :data:`PASS_RADIUS_M`: both stacks
  round the corners) and arrived at the last (within :data:`ARRIVED_M`: both
  stacks' default acceptance radius, PX4's ``NAV_ACC_RAD`` and ArduCopter's
  ``WPNAV_RADIUS``; PX4 then holds where it is);
* where it holds at the end: the distance from above to the last waypoint over
  the flight's last second;
* the engage transient: the largest tilt in the first 0.5 s.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.mission import Mission, load_mission
from sitl.lab.outer_report import mission_plan
from sitl.lab.realstack.flights import CompanionRun, Session
from sitl.lab.realstack.gcs import GroundStation, MissionItem, Telemetry
from sitl.lab.realstack.modes import gcs_time_of_boot, settle, start_mode_companion, tilt_deg

__all__ = [
    "ARRIVED_M",
    "ARRIVED_UP_M",
    "PASS_RADIUS_M",
    "SQUARE_MISSION",
    "STACK_MISSIONS",
    "MissionFlight",
    "StackMission",
    "completed_at",
    "fly_companion_mission",
    "fly_stack_mission",
    "load_square",
    "mission_figures",
    "offset_lat_lon",
    "progress",
    "start_mission_companion",
]

SQUARE_MISSION = Path(__file__).with_name("square_mission.yaml")
PASS_RADIUS_M = 3.0
"""A waypoint before the last counts as passed within this distance (from above)."""
ARRIVED_M = 2.0
"""At the last waypoint: within this distance from above, and :data:`ARRIVED_UP_M`
in height."""
ARRIVED_UP_M = 1.0
_SLOW_M_S = 0.3
EARTH_RADIUS_M = 6_371_000.0
_ENGAGE_TILT_S = 0.5
_NAV_WAYPOINT = 16
_MISSION_ITEM_REACHED = "MISSION_ITEM_REACHED"


@dataclass(frozen=True)
class StackMission:
    """How a stack flies a mission of its own."""

    mode: tuple[float, float]
    """DO_SET_MODE param2, param3 of its mission mode."""
    custom_mode: int
    """That mode as its HEARTBEAT shows it."""
    speed_param: str
    """Its leg speed's parameter, and how many of its units make 1 m/s."""
    speed_units: float
    home_first: bool
    """Its mission's item 0 is home (ArduPilot): the waypoints follow it."""
    yaw: float
    """NAV_WAYPOINT param4: NaN is PX4's own heading behaviour (MAV_CMD spec)."""

    def items(self, origin: tuple[float, float, float], mission: Mission) -> list[MissionItem]:
        """The waypoints from ``origin`` (latitude, longitude deg, height above home m)."""
        lat, lon, alt = origin
        out = [MissionItem(_NAV_WAYPOINT, lat, lon, 0.0)] if self.home_first else []
        for w in mission.waypoints:
            wlat, wlon = offset_lat_lon(lat, lon, w.north_m, w.east_m)
            out.append(
                MissionItem(_NAV_WAYPOINT, wlat, wlon, alt + w.up_m, (w.hold_s, 0.0, 0.0, self.yaw))
            )
        return out


STACK_MISSIONS = {
    "px4": StackMission((4.0, 4.0), (4 << 16) | (4 << 24), "MPC_XY_CRUISE", 1.0, False, math.nan),
    "ardupilot": StackMission((3.0, 0.0), 3, "WPNAV_SPEED", 100.0, True, 0.0),
}
"""PX4 AUTO.MISSION (``MPC_XY_CRUISE``, m/s); ArduCopter AUTO (``WPNAV_SPEED``, cm/s)."""


def offset_lat_lon(
    lat_deg: float, lon_deg: float, north_m: float, east_m: float
) -> tuple[float, float]:
    """The point ``north_m``, ``east_m`` from (``lat_deg``, ``lon_deg``) on a sphere of
    :data:`EARTH_RADIUS_M`, in the tangent plane (exact enough within a few hundred
    metres: both stacks project the same way).

    .. math:: \\Delta\\varphi = n / R, \\qquad \\Delta\\lambda = e / (R \\cos\\varphi)
    """
    dlat = math.degrees(north_m / EARTH_RADIUS_M)
    dlon = math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat_deg))))
    return lat_deg + dlat, lon_deg + dlon


@dataclass
class MissionFlight:
    """One flight of the mission, in the ground station's clock."""

    who: str
    t_start_s: float
    """The switch high, or the stack's mission mode asked for."""
    t_engaged_s: float
    """When the flyer took over: the companion's first command flown, or the stack's ACK."""
    plan: np.ndarray
    """The start and the waypoints, NED (n, 3), in LOCAL_POSITION_NED's frame."""
    reported_done: bool
    """The flyer said it reached the last waypoint."""
    attitude: list[tuple[float, ...]]
    """(t, roll, pitch) rows."""
    position: list[tuple[float, ...]]
    """(t, x, y, z, vx, vy, vz) rows, NED."""
    run: CompanionRun | None = None


def start_mission_companion(session: Session, path: Path, *args: str) -> CompanionRun:
    """``companion run --engage rc-switch --mode position --mission path *args``,
    started and ready (it waits for the switch)."""
    return start_mode_companion(session, "position", "--mission", str(path), *args)


def _arrived(g: GroundStation, plan: np.ndarray) -> bool:
    pos = g.now.position_ned_m
    if pos is None:
        return False
    end = plan[-1]
    return bool(
        math.hypot(pos[0] - end[0], pos[1] - end[1]) <= ARRIVED_M
        and abs(pos[2] - end[2]) <= ARRIVED_UP_M
    )


def _slow(now: Telemetry) -> bool:
    v = now.velocity_ned_m_s
    return v is not None and math.hypot(v[0], v[1]) < _SLOW_M_S


def _settle_s(g: GroundStation, still_s: float, timeout_s: float) -> None:
    """Until the vehicle has been slow for ``still_s`` (an overshoot's turning point
    is not the end), or ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    since: float | None = None
    while time.monotonic() < deadline:
        if not _slow(g.now):
            since = None
        elif since is None:
            since = time.monotonic()
        elif time.monotonic() - since >= still_s:
            return
        time.sleep(0.05)


def _until_arrived(
    g: GroundStation, plan: Callable[[], np.ndarray | None], said_done: Callable[[], bool],
    timeout_s: float,
) -> bool:  # fmt: skip
    """Until the flyer said it reached the last waypoint and the vehicle is there
    (True), or ``timeout_s`` (False); then until it has been slow for a second
    (6 s at most)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        p = plan()
        if p is not None and said_done() and _arrived(g, p):
            _settle_s(g, 1.0, 6.0)
            return True
        time.sleep(0.1)
    return False


def _record(
    session: Session, who: str, t0: float, t_eng: float, plan: np.ndarray, done: bool,
    until_s: float,
) -> MissionFlight:  # fmt: skip
    g = session.gcs
    assert g is not None
    att = g.series("ATTITUDE", "roll", "pitch", since_s=t0 - 1.0)
    pos = g.series("LOCAL_POSITION_NED", "x", "y", "z", "vx", "vy", "vz", since_s=t0 - 1.0)
    return MissionFlight(
        who, t0, t_eng, plan, done,
        [r for r in att if r[0] <= until_s], [r for r in pos if r[0] <= until_s],
    )  # fmt: skip


_MISSION_CURRENT = "MISSION_CURRENT"


def _from_the_first_item(
    g: GroundStation, first: int, since_s: float, timeout_s: float = 4.0
) -> None:
    """The stack's current mission item made ``first`` (MISSION_SET_CURRENT) until its
    MISSION_CURRENT (1 Hz) since ``since_s`` says so, within ``timeout_s``. Over a new
    upload of the same waypoints, PX4 v1.16 kept the last item of the mission it had
    flown current (MISSION_CURRENT seq 3 of 4): its mission mode then flew that item
    alone (a 3 m climb) and said "Mission finished, loitering". It answers
    MAV_CMD_DO_SET_MISSION_CURRENT with "command 224 unsupported"."""
    deadline = time.monotonic() + timeout_s
    next_ask = 0.0
    while time.monotonic() < deadline:
        got = g.series(_MISSION_CURRENT, "seq", since_s=since_s)
        if got and got[-1][1] == first:
            return
        if time.monotonic() >= next_ask:
            g.send("mission_set_current_send", g.target, 1, first)
            next_ask = time.monotonic() + 1.0
        time.sleep(0.05)


def fly_stack_mission(session: Session, mission: Mission, timeout_s: float = 60.0) -> MissionFlight:
    """The mission uploaded to the stack and flown in its mission mode, from the
    hold and back to it; its leg speed the mission's for the flight."""
    g = session.gcs
    assert g is not None
    how = STACK_MISSIONS[session.name]
    g.record_types.update((_MISSION_ITEM_REACHED, _MISSION_CURRENT))
    settle(session)
    got = g.param_get(how.speed_param)
    if got is None:
        raise RuntimeError(f"{session.name} has no {how.speed_param}")
    g.param_set(how.speed_param, mission.speed_m_s * how.speed_units)
    try:
        pos = g.now.position_ned_m
        assert pos is not None
        origin = g.global_position()
        plan = np.array(
            [pos] + [(pos[0] + w.north_m, pos[1] + w.east_m, pos[2] - w.up_m)
                     for w in mission.waypoints]
        )  # fmt: skip
        items = how.items(origin, mission)
        res = g.upload_mission(items)
        if res != 0:
            raise RuntimeError(f"{session.name} refused the mission ({res}): {g.texts[-3:]}")
        _from_the_first_item(g, int(how.home_first), g.clock())
        # PX4 checks an uploaded mission before it may fly it ("Switching to Mission
        # is currently not available" until then): asked again, within a bound.
        for _ in range(6):
            t0 = g.clock()
            res = g.set_mode(*how.mode)
            t_eng = g.clock()
            # PX4's heartbeat shows a mode once a second: the ACK alone is not enough.
            if res == 0 and g.wait(lambda t: t.mode == how.custom_mode, 1.5):
                break
            time.sleep(0.5)
        else:
            raise RuntimeError(f"{session.name} did not fly its mission: {g.texts[-3:]}")
        last = len(items) - 1

        def said_done() -> bool:
            return any(s.fields["seq"] == last for s in g.records.get(_MISSION_ITEM_REACHED, [])
                       if s.t_s >= t0)  # fmt: skip

        _until_arrived(g, lambda: plan, said_done, timeout_s)
        flight = _record(session, "stack", t0, t_eng, plan, said_done(), g.clock())
    finally:
        g.param_set(how.speed_param, got[0])
        session.hold()
    return flight


def fly_companion_mission(
    session: Session, run: CompanionRun, mission: Mission, timeout_s: float = 60.0
) -> MissionFlight:
    """The mission with the companion ``run`` (:func:`start_mission_companion`),
    engaged by the pilot's switch from the hold, the sticks centred; the switch low
    once it has arrived (the companion hands back), the run stopped, then the hold."""
    g = session.gcs
    assert g is not None
    settle(session)
    sw = session.pilot
    sw.pilot = None  # centred sticks, the switch high
    n = len(mission.waypoints)
    said = f"{n} of {n}: holding there"
    t0 = g.clock()
    sw.engage(t0)
    try:
        if not session.wait_engaged(run, 5.0):
            raise RuntimeError(f"companion did not engage: {run.events()[-5:]}")
        _until_arrived(
            g,
            lambda: mission_plan(mission, run.events()),
            lambda: said in run.details("mission_waypoint"),
            timeout_s,
        )
    finally:
        sw.release()
    t_end = g.clock()
    time.sleep(1.0)
    run.stop()
    plan = mission_plan(mission, run.events())
    if plan is None:
        raise RuntimeError(f"companion did not start the mission: {run.events()[-5:]}")
    cols = run.control()
    flown = cols["engaged"] > 0.5
    t_eng = t0
    if flown.any():
        t_eng = gcs_time_of_boot(session, float(cols["t_s"][flown][0]))
    done = said in run.details("mission_waypoint")
    flight = _record(session, "companion", t0, t_eng, plan, done, t_end)
    flight.run = run
    session.hold()
    return flight


def progress(pos_ned: np.ndarray, plan: np.ndarray) -> np.ndarray:
    """Per position: the index in ``plan`` of the waypoint being flown to, the
    waypoints passed in order (within :data:`PASS_RADIUS_M` from above)."""
    k, out = 1, np.empty(len(pos_ned), dtype=int)
    for i, p in enumerate(pos_ned):
        if k < len(plan) - 1 and math.hypot(*(p[:2] - plan[k, :2])) <= PASS_RADIUS_M:
            k += 1
        out[i] = k
    return out


def _legs(
    points_ne: np.ndarray, to_wp: np.ndarray, plan: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per point (n, 2): the distance from above to the closest leg of ``plan``
    (m, 3, NED) among the one flown (to waypoint ``to_wp``), the one before and the
    one after (a square's start and end are one point: the first and last legs are
    both closest there), and the leg's down coordinate there."""
    best = np.full(len(points_ne), np.inf)
    down = np.zeros(len(points_ne))
    for j, (a, b) in enumerate(itertools.pairwise(plan)):
        ab = b[:2] - a[:2]
        den = float(ab @ ab)
        s = np.zeros(len(points_ne)) if den == 0.0 else (points_ne - a[:2]) @ ab / den
        s = np.clip(s, 0.0, 1.0)
        d = np.linalg.norm(points_ne - (a[:2] + s[:, None] * ab), axis=1)
        closer = (d < best) & (np.abs(to_wp - 1 - j) <= 1)
        best[closer] = d[closer]
        down[closer] = (a[2] + s * (b[2] - a[2]))[closer]
    return best, down


def completed_at(t: np.ndarray, pos_ned: np.ndarray, plan: np.ndarray) -> float | None:
    """When the vehicle had passed each waypoint in order (:func:`progress`) and
    arrived at the last (:data:`ARRIVED_M`, :data:`ARRIVED_UP_M`); None if it did not."""
    last = len(plan) - 1
    d_h = np.hypot(*(pos_ned[:, :2] - plan[last, :2]).T)
    at = (progress(pos_ned, plan) == last) & (d_h <= ARRIVED_M)
    at &= np.abs(pos_ned[:, 2] - plan[last, 2]) <= ARRIVED_UP_M
    return float(t[at][0]) if at.any() else None


def mission_figures(flight: MissionFlight) -> dict[str, Any]:
    """The figures of one flight (module docstring), rounded; NaN where a window
    holds no sample."""
    t0, te = flight.t_start_s, flight.t_engaged_s
    att = np.asarray(flight.attitude, dtype=float).reshape(-1, 3)
    pos = np.asarray(flight.position, dtype=float).reshape(-1, 7)
    ta, tilt = att[:, 0], np.array([tilt_deg(r, p) for _, r, p in att])
    tp = pos[:, 0]
    after = tp >= te
    tc = completed_at(tp[after], pos[after, 1:4], flight.plan)
    end = tc if tc is not None else float(tp[-1])
    w = (tp >= te) & (tp <= end)
    wa = (ta >= te) & (ta <= end)
    d_h, down = _legs(pos[w, 1:3], progress(pos[w, 1:4], flight.plan), flight.plan)
    d_up = down - pos[w, 3]
    speed = np.hypot(pos[w, 4], pos[w, 5])
    last_s = tp >= tp[-1] - 1.0
    end_offset = np.hypot(*(pos[last_s, 1:3] - flight.plan[-1, :2]).T)
    return {
        "who": flight.who,
        "completed": bool(flight.reported_done and tc is not None),
        "time_to_complete_s": round(tc - t0, 2) if tc is not None else math.nan,
        "engage_after_s": round(te - t0, 2),
        "engage_tilt_deg": _max(tilt[(ta >= te) & (ta <= te + _ENGAGE_TILT_S)]),
        "path_rms_m": _rms(d_h),
        "path_max_m": _max(d_h),
        "alt_rms_m": _rms(d_up),
        "alt_max_m": _max(np.abs(d_up)),
        "tilt_max_deg": _max(tilt[wa]),
        "speed_max_m_s": _max(speed),
        "speed_mean_m_s": round(float(speed.mean()), 3) if speed.size else math.nan,
        "end_offset_m": round(float(end_offset.mean()), 3),
    }


def _max(x: np.ndarray) -> float:
    return round(float(np.max(x)), 3) if x.size else math.nan


def _rms(x: np.ndarray) -> float:
    return round(float(np.sqrt(np.mean(x**2))), 3) if x.size else math.nan


def load_square() -> Mission:
    """:data:`SQUARE_MISSION`, read."""
    return load_mission(SQUARE_MISSION)
