"""The link model (sitl.link_model): what a link does to each message, and ``--link``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sitl.link_model import DOWN, LINK_PROFILES, UP, LinkModel, LinkSpec, parse_link

IMU, RC = 105, 65


def _spec(**kw: float | bool) -> LinkSpec:
    fields: dict[str, float | bool] = {
        "up_delay_s": 0.010,
        "up_jitter_s": 0.005,
        "down_delay_s": 0.004,
        "down_jitter_s": 0.002,
    }
    return LinkSpec(**{**fields, **kw})


def _send(
    model: LinkModel, n: int, stream: int = IMU, period_s: float = 0.001
) -> list[tuple[float, ...]]:
    return [model.arrivals(UP, stream, k * period_s) for k in range(n)]


def test_the_same_seed_gives_the_same_arrivals_and_another_seed_others() -> None:
    spec = _spec(loss=0.1, duplicate=0.1, fifo=False)
    a, b, c = LinkModel(spec, 7), LinkModel(spec, 7), LinkModel(spec, 8)
    got = [_send(m, 500) for m in (a, b, c)]
    assert got[0] == got[1]
    assert got[0] != got[2]
    assert a.counts() == b.counts()


def test_a_stream_draws_the_same_whatever_another_stream_sent() -> None:
    spec = _spec(loss=0.1, duplicate=0.1, fifo=False)
    quiet, busy = LinkModel(spec, 3), LinkModel(spec, 3)
    imu_quiet, imu_busy = [], []
    for k in range(300):
        t = k * 0.001
        if k % 10 == 0:
            quiet.arrivals(UP, RC, t)
        for _ in range(5):  # a chatty stream, and the other direction
            busy.arrivals(UP, RC, t)
            busy.arrivals(DOWN, IMU, t)
        imu_quiet.append(quiet.arrivals(UP, IMU, t))
        imu_busy.append(busy.arrivals(UP, IMU, t))
    assert imu_quiet == imu_busy


def test_a_fifo_link_never_reorders_a_stream() -> None:
    # Jitter (+-9 ms) far above the spacing (1 ms), duplicates too.
    model = LinkModel(_spec(up_delay_s=0.010, up_jitter_s=0.009, duplicate=0.3), 1)
    times = [t for arr in _send(model, 2000) for t in arr]
    assert len(times) > 2000  # duplicates came
    assert np.all(np.diff(times) >= 0.0)


def test_a_link_that_is_not_fifo_reorders() -> None:
    model = LinkModel(_spec(up_delay_s=0.010, up_jitter_s=0.009, fifo=False), 1)
    times = [t for arr in _send(model, 2000) for t in arr]
    assert np.sum(np.diff(times) < 0.0) > 100


def test_loss_and_duplicate_rates_are_near_the_spec() -> None:
    n = 20000
    model = LinkModel(_spec(loss=0.1, duplicate=0.2), 5)
    arrivals = _send(model, n)
    lost = sum(1 for a in arrivals if not a)
    doubled = sum(1 for a in arrivals if len(a) == 2)
    c = model.counts()
    assert (c["up_sent"], c["up_lost"], c["up_duplicated"]) == (n, lost, doubled)
    assert c["down_sent"] == 0
    # Binomial: 3 sigma is under 0.7 % of n for both.
    assert abs(lost / n - 0.1) < 0.007
    assert abs(doubled / n - 0.2 * 0.9) < 0.009  # a lost message is not duplicated


@pytest.mark.parametrize("fifo", [True, False])
def test_every_delay_is_within_delay_plus_minus_jitter(fifo: bool) -> None:
    model = LinkModel(_spec(duplicate=0.2, fifo=fifo), 2)
    for direction, (d, j) in ((UP, (0.010, 0.005)), (DOWN, (0.004, 0.002))):
        delays = [
            a - k * 0.001 for k in range(3000) for a in model.arrivals(direction, IMU, k * 0.001)
        ]
        assert min(delays) >= d - j - 1e-12
        assert max(delays) <= d + j + 1e-12
        if not fifo:  # (FIFO holds a fast one behind the one before: fewer short delays)
            assert max(delays) - min(delays) > 1.9 * j  # the jitter spans its range


def test_a_delay_is_never_negative() -> None:
    model = LinkModel(_spec(up_delay_s=0.001, up_jitter_s=0.003, fifo=False), 2)
    delays = [a - k * 0.001 for k, arr in enumerate(_send(model, 1000)) for a in arr]
    assert min(delays) == 0.0


def test_the_ideal_link_is_ideal_and_the_others_are_not() -> None:
    assert LINK_PROFILES["ideal"].ideal
    assert LinkSpec(fifo=False).ideal  # nothing to reorder without jitter
    for name, spec in LINK_PROFILES.items():
        assert spec.ideal == (name == "ideal")
    assert not LinkSpec(loss=0.01).ideal


# --------------------------------------------------------------------- parse_link


@pytest.mark.parametrize("name", list(LINK_PROFILES))
def test_a_profile_by_name(name: str) -> None:
    assert parse_link(name) == LINK_PROFILES[name]
    assert parse_link(f" {name} ") == LINK_PROFILES[name]


def test_fields_set_both_directions_or_one() -> None:
    spec = parse_link("delay_ms=10,jitter_ms=5,loss=0.01,duplicate=0.02,fifo=false")
    assert (spec.up_delay_s, spec.down_delay_s) == (0.010, 0.010)
    assert (spec.up_jitter_s, spec.down_jitter_s) == (0.005, 0.005)
    assert (spec.loss, spec.duplicate, spec.fifo) == (0.01, 0.02, False)
    assert spec.name == "custom"
    one = parse_link("up_delay_ms=3, down_jitter_ms=1")
    assert (one.up_delay_s, one.up_jitter_s, one.down_delay_s, one.down_jitter_s) == (
        0.003,
        0.0,
        0.0,
        0.001,
    )
    assert parse_link("delay_ms=0") == LinkSpec(name="custom")
    assert parse_link("delay_ms=0").ideal


def test_a_profile_with_fields_changed() -> None:
    spec = parse_link("wifi,loss=0,down_delay_ms=20")
    wifi = LINK_PROFILES["wifi"]
    assert spec.loss == 0.0
    assert spec.down_delay_s == 0.020
    assert (spec.up_delay_s, spec.up_jitter_s, spec.fifo) == (
        wifi.up_delay_s,
        wifi.up_jitter_s,
        wifi.fifo,
    )
    assert spec.name == "wifi*"
    assert "wifi*" in spec.describe() and "reordering" in spec.describe()


@pytest.mark.parametrize(
    ("text", "named"),
    [
        ("", "expected a profile"),
        (" , ", "expected a profile"),
        ("bogus", "'bogus'"),
        ("uart,delay_ms", "'delay_ms' is not KEY=VALUE"),
        ("delay_ms=5,speed=3", "'speed'"),
        ("delay_ms=-1", "delay_ms='-1'"),
        ("delay_ms=2000", "delay_ms='2000'"),
        ("jitter_ms=inf", "jitter_ms='inf'"),
        ("up_delay_ms=nan", "up_delay_ms='nan'"),
        ("loss=0.9", "loss='0.9'"),
        ("duplicate=-0.1", "duplicate='-0.1'"),
        ("loss=nan", "loss='nan'"),
        ("fifo=maybe", "fifo='maybe'"),
        ("delay_ms=x", "delay_ms='x'"),
        ("loss=lots", "loss='lots'"),
    ],
)
def test_bad_link_text_names_the_bad_part(text: str, named: str) -> None:
    with pytest.raises(ValueError) as err:
        parse_link(text)
    assert named in str(err.value)


# ------------------------------------------------------------------- sitl run --link


@pytest.mark.parametrize(
    ("value", "said"), [("bogus", "unknown profile 'bogus'"), ("delay_ms=5,fifo=2", "fifo='2'")]
)
def test_sitl_run_refuses_a_bad_link_before_starting(value: str, said: str) -> None:
    from click.testing import CliRunner

    from sitl.cli import cli

    profile = Path(__file__).resolve().parents[2] / "vehicle_profiles" / "f450.yaml"
    result = CliRunner().invoke(cli, ["run", "--profile", str(profile), "--link", value])
    assert result.exit_code == 2
    assert "'--link'" in result.output and said in result.output


def test_sitl_run_help_lists_the_link_profiles() -> None:
    from click.testing import CliRunner

    from sitl.cli import cli

    result = CliRunner().invoke(cli, ["run", "--help"])
    assert result.exit_code == 0
    for name in LINK_PROFILES:
        assert name in result.output
