"""Flights the real-stack tests share: the hand-back cases and how each is judged."""

from __future__ import annotations

import contextlib
import statistics
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.stacks import ARDUPILOT, PX4, FlightStack
from sitl.lab.realstack.flights import Session
from sitl.pilot.factory import make_pilot

WATCH_S = 5.0
"""How long the stack is watched after the hand-back (the companion's own watch is 3 s)."""
_STACKS = {"px4": PX4, "ardupilot": ARDUPILOT}


@dataclass(frozen=True)
class HandbackCase:
    """A safe mode asked for, with the pilot's input present (the switch goes low) or
    absent (the pilot's input is lost while engaged)."""

    stack: str
    safe_mode: str
    pilot_present: bool

    @property
    def id(self) -> str:
        return f"{self.safe_mode}-{'pilot' if self.pilot_present else 'no-pilot'}"

    @property
    def dialect(self) -> FlightStack:
        return _STACKS[self.stack]

    def check(self, out: dict[str, Any]) -> None:
        """What a serious user must see: a mode the vehicle can fly on its own, held."""
        st = self.dialect
        end = out["end_mode"]
        manual = {st.mode_label(m) for m in st.pilot_modes}
        if self.pilot_present:
            asked = st.mode(self.safe_mode).name.upper()
            assert out["handed_back"][-1].endswith(f"-> {asked} accepted"), out
            # PX4 gives a pilot who moves the sticks in Hold or Land Position mode
            # ("Pilot took over using sticks", COM_RC_OVERRIDE): the pilot has it.
            took_over = any(t.startswith("Pilot took over") for t in out["said"])
            assert end == asked or (took_over and end in manual), out
            assert not out["failsafe_at_end"], out
            mode = st.mode(self.safe_mode)
            if self.safe_mode != "land" and st.custom_mode(mode) not in st.throttle_modes:
                # The modes that hold altitude hold it; with the throttle stick as the
                # collective (STABILIZE, MANUAL) the pilot holds it, not the mode.
                assert abs(out["altitude_change_m"]) < 4.0, out
        else:
            assert end not in manual, out  # never a manual mode without the pilot
            for text in out["handed_back"]:
                chosen = text.rsplit("-> ", 1)[-1].split(" ")[0]
                assert chosen not in manual, out
            assert out["exit"] == 3, out  # a failsafe, then the run's end


def handback_cases(stack: str) -> list[HandbackCase]:
    """Every safe mode of the stack, with the pilot and without; land last (it lands)."""
    modes = [m for m in _STACKS[stack].safe_modes if m != "land"] + ["land"]
    return [HandbackCase(stack, m, present) for m in modes for present in (True, False)]


def fly_safe_mode_case(
    session: Session, case: HandbackCase, args: tuple[str, ...]
) -> dict[str, Any]:
    """Engage, fly 2 s of hover, then hand back as the case says; watch ``WATCH_S``."""
    g = session.gcs
    assert g is not None
    session.ensure_airborne(15.0)
    run = session.start_companion(
        "--engage", "rc-switch", *args, "--safe-mode", case.safe_mode, name=f"handback-{case.id}"
    )
    pilot = session.pilot
    engaged = _engage_hovering(session, run, 1.5)
    t0 = g.clock()
    alt0 = _altitude(session)
    if case.pilot_present:
        pilot.release()
    else:
        session.lose_pilot()
    time.sleep(WATCH_S)
    st = case.dialect
    statuses = [s for t, _m, _a, s in g.heartbeats if t >= t0]
    out: dict[str, Any] = {
        "engaged": engaged,
        "end_mode": st.mode_label(g.now.mode or 0),
        "failsafe_seen": any(s in (5, 6) for s in statuses),
        "failsafe_at_end": g.now.system_status in (5, 6),
        "altitude_change_m": round(_altitude(session) - alt0, 2),
        "handed_back": run.details("handed_back"),
        "said": [t for t in g.texts_since(t0)][:5],
    }
    out["exit"] = run_exit(run, ends_itself=not case.pilot_present)
    session.restore_pilot()
    pilot.pilot = None
    return out


RUN_END_S = 10.0
"""How long a run that ends by itself (a failsafe, then its end) is given to finish
after the watch: on a loaded machine its end (files closed) came after the 5 s
watch, and the run was counted as still flying (exit -15, from the harness's stop)."""


def run_exit(run: Any, *, ends_itself: bool) -> int:
    """The run's exit code; one that ends by itself is waited for up to
    :data:`RUN_END_S`, any other (or one still running then) is stopped."""
    if ends_itself:
        with contextlib.suppress(subprocess.TimeoutExpired):
            return int(run.proc.wait(timeout=RUN_END_S))
    code = run.proc.poll()
    return int(code) if code is not None else int(run.stop())


def _engage_hovering(session: Session, run: Any, hover_s: float) -> bool:
    """The pilot flips the switch high with a hovering pilot; whether the companion
    engaged within 5 s; then ``hover_s`` of hover."""
    g = session.gcs
    assert g is not None
    session.pilot.pilot = make_pilot("hover", rng=np.random.default_rng(0))
    session.pilot.engage(g.clock())
    engaged = session.wait_engaged(run, 5.0)
    time.sleep(hover_s)
    return engaged


def _altitude(session: Session) -> float:
    g = session.gcs
    pos = g.now.position_ned_m if g is not None else None
    return float("nan") if pos is None else -pos[2]


FAILSAFE_KINDS = ("link-cut", "imu-stopped", "companion-killed")
"""What can be made real on the real stacks beside the pilot's input lost (the
hand-back cases): the link cut both ways for 3 s, the IMU stream stopped, the
companion killed (SIGKILL), each while it hovers the vehicle."""


def fly_failsafe_case(session: Session, kind: str, args: tuple[str, ...]) -> dict[str, Any]:
    """Engage through a relay, hover 2 s, make ``kind`` happen; watch ``WATCH_S``."""
    import signal

    from sitl.lab.fly import free_udp_port
    from sitl.lab.realstack.cutter import LinkCutter

    g = session.gcs
    assert g is not None
    session.ensure_airborne(15.0)
    port = int(session.stack.companion_url.rsplit(":", 1)[1])
    q = free_udp_port()
    cutter = LinkCutter(port, q)
    try:
        run = session.start_companion(
            "--engage", "rc-switch", *args, name=f"failsafe-{kind}",
            connect_url=f"udpin:127.0.0.1:{q}",
        )  # fmt: skip
        pilot = session.pilot
        engaged = _engage_hovering(session, run, 2.0)
        t0 = g.clock()
        alt0 = _altitude(session)
        if kind == "link-cut":
            cutter.cut()
            time.sleep(3.0)
            cutter.restore()
        elif kind == "imu-stopped":
            cutter.drop_messages({105, 30})  # HIGHRES_IMU, ATTITUDE
        elif kind == "companion-killed":
            run.proc.send_signal(signal.SIGKILL)
        else:
            raise ValueError(kind)
        time.sleep(WATCH_S)
        st = _STACKS[session.name]
        statuses = [s for t, _m, _a, s in g.heartbeats if t >= t0]
        alts = [-z for t, z in g.series("LOCAL_POSITION_NED", "z", since_s=t0)]
        out: dict[str, Any] = {
            "engaged": engaged,
            "end_mode": st.mode_label(g.now.mode or 0),
            "failsafe_seen": any(s in (5, 6) for s in statuses),
            "altitude_change_m": round(_altitude(session) - alt0, 2),
            "altitude_min_change_m": round(min(alts, default=alt0) - alt0, 2),
            "companion_failsafe": [k for k in run.kinds() if k.startswith("failsafe")][:2],
            "handed_back": run.details("handed_back")[:2],
            "said": g.texts_since(t0)[:4],
        }
        out["exit"] = run_exit(run, ends_itself=True)
    finally:
        cutter.close()
        pilot.release()
        pilot.pilot = None
    return out


def preflight(session: Session, rates_args: tuple[str, ...], *args: str) -> dict[str, Any]:
    """``companion preflight --json`` against the stack: its checks by name."""
    return {c["name"]: c for c in preflight_document(session, rates_args, *args)["checks"]}


def preflight_document(session: Session, rates_args: tuple[str, ...], *args: str) -> dict[str, Any]:
    """``companion preflight --json`` against the stack: the whole document."""
    import json
    import sys

    from tests.realstack.conftest import ROOT

    cmd = [sys.executable, "-m", "companion", "preflight", "--connect",
           session.stack.companion_url, *rates_args, "--json", *args]  # fmt: skip
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.returncode in (0, 1), res.stderr
    doc: dict[str, Any] = json.loads(res.stdout)
    return doc


def flick_the_switch_while_preflight_watches(session: Session) -> None:
    """The pilot flips the engage switch high for 1 s, 4 s from now (once preflight
    has read the parameters and watches), in a thread."""
    import threading

    pilot = session.pilot

    def flick() -> None:
        time.sleep(4.0)
        pilot.switch_high = True
        time.sleep(1.0)
        pilot.switch_high = False

    threading.Thread(target=flick, daemon=True).start()


def real_time_factor(session: Session, since_s: float, until_s: float) -> float:
    """The stack's clock over the ground station's between ``since_s`` and
    ``until_s`` on the ground station's clock (ATTITUDE's ``time_boot_ms``
    against when each arrived): below 1 where the stack runs behind real time."""
    g = session.gcs
    assert g is not None
    rows = [r for r in g.records.get("ATTITUDE", []) if since_s <= r.t_s <= until_s]
    boot_s = (rows[-1].fields["time_boot_ms"] - rows[0].fields["time_boot_ms"]) * 1e-3
    return boot_s / (rows[-1].t_s - rows[0].t_s)


AXES = ("roll", "pitch", "yaw")
"""The body-rate axes, in the order the rate errors give them."""


def fly_rates_pair(session: Session, rates_args: tuple[str, ...], seed: int) -> dict[str, Any]:
    """The same acro-mixed flight passed through and flown by MFC: the rate MAE of each
    (deg/s), the failsafes each met, and what ``--rates-law-axes auto`` chose."""
    from sitl.lab.realstack.flights import rate_errors

    errs: dict[str, Any] = {}
    for name, extra in (("pass-through", ("--rates-passthrough",)), ("mfc", ())):
        session.ensure_airborne(15.0)
        pilot = make_pilot("acro-mixed", rng=np.random.default_rng(seed))
        run = session.fly(
            *rates_args, *extra, pilot=pilot, duration_s=pilot.duration_s, name=f"rates-{name}"
        )
        assert "engaged" in run.kinds(), run.events()
        errs[name] = rate_errors(run.control())
        errs[name]["failsafes"] = [k for k in run.kinds() if k.startswith("failsafe")]
        errs[name]["rates_law_axes"] = run.details("rates_law_axes")  # auto's choice
    return errs


def median_of_pairs(pairs: list[dict[str, Any]]) -> dict[str, Any]:
    """:func:`fly_rates_pair`'s results as one: each law's MAE per axis the median over
    the pairs, its samples summed, and the failsafes and auto's choices of every pair."""
    out: dict[str, Any] = {}
    for law in ("pass-through", "mfc"):
        runs = [p[law] for p in pairs]
        out[law] = {a: round(statistics.median(r[a] for r in runs), 2) for a in AXES}
        out[law]["n"] = sum(r["n"] for r in runs)
        out[law]["failsafes"] = [k for r in runs for k in r["failsafes"]]
        out[law]["rates_law_axes"] = [c for r in runs for c in r["rates_law_axes"]]
    return out


def check_failsafe_case(session: Session, kind: str, out: dict[str, Any]) -> None:
    """Whatever the stack does on its own, the vehicle keeps flying level and high;
    unless the companion died, it handed back (across a cut link, once it is back)
    to a mode the vehicle flies alone."""
    assert out["engaged"], out
    assert out["altitude_min_change_m"] > -4.0, out
    if kind != "companion-killed":
        assert out["end_mode"] != session.stack_dialect.engage_label, out
        assert out["companion_failsafe"][:1] == ["failsafe_stale_imu"], out
        assert out["exit"] == 3, out


def send_a_signing_key(session: Session, folder: Any) -> Any:
    """A random key sent in SETUP_SIGNING from the ground station (as MAVProxy's
    ``signing setup`` does), and the companion's key file holding it."""
    import secrets

    g = session.gcs
    assert g is not None
    key = secrets.token_bytes(32)
    path = folder / "signing.key"
    path.write_text(key.hex() + "\n")
    path.chmod(0o600)
    stamp = int((time.time() - 1_420_070_400) * 1e5)  # 10 us since 2015-01-01 (MAVLink's)
    g.send("setup_signing_send", g.target, 1, list(key), stamp)
    time.sleep(1.0)
    return path


@contextlib.contextmanager
def params_set(session: Session, params: dict[str, float]) -> Iterator[None]:
    """``params`` set on the stack for the block, and set back after it."""
    g = session.gcs
    assert g is not None
    before = {}
    try:
        for name, value in params.items():
            got = g.param_get(name)
            assert got is not None, name
            before[name] = got[0]
            g.param_set(name, value)
        yield
    finally:
        for name, value in before.items():
            g.param_set(name, value)


def preflight_with(
    session: Session, rates_args: tuple[str, ...], params: dict[str, float]
) -> dict[str, Any]:
    """Preflight's checks with ``params`` set on the stack (set back afterwards)."""
    with params_set(session, params):
        return preflight(session, rates_args, "--watch-s", "2")
