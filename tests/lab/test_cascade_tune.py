"""The per-vehicle retuning of PX4's cascade: its search space (the flights are the lab's)."""

from __future__ import annotations

import dataclasses

from sitl.lab.cascade_pid import PX4_DEFAULT_CASCADE
from sitl.lab.cascade_tune import SPAN, TUNED_FIELDS, candidates


def test_the_default_comes_first_and_the_draws_stay_within_the_span() -> None:
    cands = candidates(20, seed=3)
    assert len(cands) == 20 and cands[0] == PX4_DEFAULT_CASCADE
    for g in cands[1:]:
        for f in TUNED_FIELDS:
            ratio = getattr(g, f) / getattr(PX4_DEFAULT_CASCADE, f)
            assert 1.0 / SPAN <= ratio <= SPAN, (f, ratio)
        untouched = {
            f.name for f in dataclasses.fields(PX4_DEFAULT_CASCADE) if f.name not in TUNED_FIELDS
        }
        for f in untouched:
            assert getattr(g, f) == getattr(PX4_DEFAULT_CASCADE, f)
    assert len({g.xy_p_1_s for g in cands}) == 20  # every draw its own


def test_the_same_seed_draws_the_same_candidates() -> None:
    assert candidates(8, seed=5) == candidates(8, seed=5)
    assert candidates(8, seed=5) != candidates(8, seed=6)
