"""Scripted references: the file format, its errors, and interpolation."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from companion.errors import ConfigError
from companion.reference import load_reference


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "ref.csv"
    p.write_text(text, encoding="utf-8")
    return p


def test_interpolates_and_holds(tmp_path: Path) -> None:
    ref = load_reference(
        write(tmp_path, "t_s,roll_deg_s,pitch_deg_s,yaw_deg_s\n0,0,0,0\n1,100,-50,10\n")
    )
    rates, thrust = ref.at(0.5)
    assert rates == pytest.approx((math.radians(50), math.radians(-25), math.radians(5)))
    assert thrust is None  # the pilot's throttle
    assert ref.at(-1.0)[0] == pytest.approx((0.0, 0.0, 0.0))
    assert ref.at(5.0)[0] == pytest.approx((math.radians(100), math.radians(-50), math.radians(10)))


def test_thrust_column(tmp_path: Path) -> None:
    ref = load_reference(
        write(tmp_path, "t_s,roll_deg_s,pitch_deg_s,yaw_deg_s,thrust\n0,0,0,0,0.4\n2,0,0,0,0.6\n")
    )
    assert ref.at(1.0)[1] == pytest.approx(0.5)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("roll,pitch\n0,0\n", "line 1: expected the header"),
        ("t_s,roll_deg_s,pitch_deg_s,yaw_deg_s\n0,0,0\n", "line 2: expected 4 values"),
        ("t_s,roll_deg_s,pitch_deg_s,yaw_deg_s\n0,0,0,x\n", "line 2: expected numbers"),
        ("t_s,roll_deg_s,pitch_deg_s,yaw_deg_s\n1,0,0,0\n1,0,0,0\n", "line 3: t_s must increase"),
        ("t_s,roll_deg_s,pitch_deg_s,yaw_deg_s\n0,0,0,nan\n", "line 2: expected finite"),
        ("t_s,roll_deg_s,pitch_deg_s,yaw_deg_s\n0,5000,0,0\n", "beyond +/-2000"),
        ("t_s,roll_deg_s,pitch_deg_s,yaw_deg_s,thrust\n0,0,0,0,1.5\n", "thrust must be in [0, 1]"),
        ("t_s,roll_deg_s,pitch_deg_s,yaw_deg_s\n", "at least one row"),
    ],
)
def test_bad_files_name_file_and_line(tmp_path: Path, text: str, expected: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_reference(write(tmp_path, text))
    assert "ref.csv" in str(info.value) and expected in str(info.value)
