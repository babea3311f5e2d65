"""The config mutation campaign (``scripts/fuzz.py config``, sitl/lab/fuzzing/config.py) on
a small seeded sample: no config the schema and ``check-config --fly`` accept crashes
or blows up on the held-out flights. The full figure (100 mutants) comes from
``python scripts/fuzz.py config --seed 1 --n 100``."""

from __future__ import annotations

import pytest

from sitl.lab.fuzzing.config import campaign, mutants


def test_mutants_are_seeded() -> None:
    assert mutants(1, 4) == mutants(1, 4)
    assert mutants(1, 4) != mutants(2, 4)


# 47 s on one worker (the default suite's slowest test): in the long tier, which CI runs too.
@pytest.mark.long
def test_no_accepted_config_crashes_or_blows_up_on_held_out_flights() -> None:
    report = campaign(seed=1, n=4, workers=1)
    verdicts = [r["verdict"] for r in report["records"]]
    assert report["violation"] == 0, [r for r in report["records"] if r["verdict"] == "violation"]
    assert report["target_met"]
    # The sample exercises both ends: some refused by the schema, some flown clean.
    assert "rejected" in verdicts and "accepted" in verdicts
    assert sum(report[k] for k in ("rejected", "failed_check", "accepted", "violation")) == 4
