"""Property tests: whatever comes in, what goes to the motors is finite and in range.

The MFC is the shipped one (companion/data/mfc_default.yaml on the F450: alpha
and the lag identified in flight, so what it learns from garbage is exercised
too); each sample is followed by ``learn()``, as in flight. Inputs are sequences
of samples (the controllers are stateful), each sample with arbitrary dt (0,
negative, huge, non-finite), rates, references and thrust. Two input spaces:

* ``plausible``: magnitudes up to 1e6 plus nan/+-inf, no subnormals; every
  field of every output must be finite;
* ``anything``: every float hypothesis can make (subnormals, 1e308); the
  motor-facing fields must be finite and in range, and nothing may raise.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from hypothesis import example, given, settings
from hypothesis import strategies as st

from companion.config import DEFAULT_CONTROLLER, build_controller, load_controller
from companion.control import (
    ControlOutput,
    MfcController,
    MixResult,
    PidController,
)
from tests.control.gains import pid_controller, px4_default_pid
from tests.control.plants import f450_mixer, f450_profile

SPECIALS = [math.nan, math.inf, -math.inf, 0.0, -0.0]

plausible = st.one_of(
    st.floats(-1e6, 1e6, allow_subnormal=False),
    st.sampled_from(SPECIALS),
)
plausible_dt = st.one_of(
    st.floats(0.0001, 0.03, allow_subnormal=False),  # around the clamp range
    st.floats(-1e6, 1e6, allow_subnormal=False),
    st.sampled_from([*SPECIALS, 0.000125, 0.02, 1e9]),
)
anything = st.floats()  # nan, +-inf, subnormals, +-1.8e308


def samples(
    x: st.SearchStrategy[float], dt: st.SearchStrategy[float]
) -> st.SearchStrategy[list[Sample]]:
    sample = st.tuples(dt, st.tuples(x, x, x), st.tuples(x, x, x), x)
    return st.lists(sample, min_size=1, max_size=30)


IDLE = 0.05
Vec3 = tuple[float, float, float]
Sample = tuple[float, Vec3, Vec3, float]


def check_motor_facing(out: ControlOutput | MixResult, n_motors: int = 4) -> None:
    torque = out.torque if isinstance(out, ControlOutput) else out.achieved
    assert len(torque) == 3
    for t in torque:
        assert math.isfinite(t) and -1.0 <= t <= 1.0, torque
    assert math.isfinite(out.thrust) and 0.0 <= out.thrust <= 1.0, out.thrust
    assert len(out.motors) == n_motors
    for m in out.motors:
        assert math.isfinite(m) and IDLE <= m <= 1.0, out.motors
    assert len(out.saturated_motors) == n_motors


def check_all_finite(out: ControlOutput) -> None:
    check_motor_facing(out)
    for field in (out.u, out.f_hat, out.error):
        assert all(math.isfinite(v) for v in field), out


SHIPPED = load_controller(DEFAULT_CONTROLLER)


def make_mfc() -> MfcController:
    ctrl = build_controller(SHIPPED, f450_profile())
    assert isinstance(ctrl, MfcController)
    assert all(a.alpha_adapt is not None for a in (SHIPPED.axes.roll, SHIPPED.axes.yaw))
    return ctrl


def make_pid() -> PidController:
    return pid_controller(px4_default_pid(), f450_mixer())


def run(
    factory: Callable[[], MfcController | PidController],
    seq: list[Sample],
    check: Callable[[ControlOutput], None],
) -> None:
    ctrl = factory()
    for dt, w, r, thrust in seq:
        check(ctrl.update(dt, w, r, thrust))
        ctrl.learn()
    # Held outputs are counted, and a reset controller is as safe as a new one.
    ctrl.reset()
    for dt, w, r, thrust in seq[:5]:
        check(ctrl.update(dt, w, r, thrust))
        ctrl.learn()


@settings(max_examples=300, deadline=None)
@given(seq=samples(plausible, plausible_dt))
def test_mfc_outputs_finite_and_in_range_plausible(seq: list[Sample]) -> None:
    run(make_mfc, seq, check_all_finite)


@settings(max_examples=300, deadline=None)
@given(seq=samples(plausible, plausible_dt))
def test_pid_outputs_finite_and_in_range_plausible(seq: list[Sample]) -> None:
    run(make_pid, seq, check_all_finite)


@settings(max_examples=300, deadline=None)
@given(seq=samples(anything, anything))
def test_mfc_motor_outputs_safe_for_any_float(seq: list[Sample]) -> None:
    run(make_mfc, seq, check_motor_facing)


@settings(max_examples=300, deadline=None)
@given(seq=samples(anything, anything))
# A yaw error of 2.5e-323 rad/s gives a yaw torque whose half underflows to 0.
@example(seq=[(0.004, (0.0, 0.0, 0.0), (0.0, 0.0, 2.5e-323), 0.5)])
def test_pid_motor_outputs_safe_for_any_float(seq: list[Sample]) -> None:
    run(make_pid, seq, check_motor_facing)


@settings(max_examples=300, deadline=None)
@given(x=st.tuples(plausible, plausible, plausible, plausible))
def test_mixer_outputs_finite_and_in_range_plausible(x: tuple[float, float, float, float]) -> None:
    check_motor_facing(f450_mixer().mix(*x))


@settings(max_examples=300, deadline=None)
@given(x=st.tuples(anything, anything, anything, anything))
def test_mixer_outputs_safe_for_any_float(x: tuple[float, float, float, float]) -> None:
    check_motor_facing(f450_mixer().mix(*x))


def test_long_run_of_random_samples_stays_finite() -> None:
    """A seeded 5000-sample stream mixing valid and garbage samples."""
    import numpy as np

    rng = np.random.default_rng(2024)
    for factory in (make_mfc, make_pid):
        ctrl = factory()
        for _ in range(5000):
            v = rng.normal(0.0, 5.0, 8)
            if rng.random() < 0.05:
                v[rng.integers(8)] = rng.choice([math.nan, math.inf, -math.inf, 1e30])
            dt = abs(v[0]) * 1e-3
            out = ctrl.update(dt, (v[1], v[2], v[3]), (v[4], v[5], v[6]), abs(v[7]) / 10)
            check_motor_facing(out)
            ctrl.learn()
