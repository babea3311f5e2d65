"""A seeded mutation campaign over the controller config (``scripts/fuzz.py config``).

Each mutant is the shipped ``mfc_default.yaml`` with one to three numeric
fields redrawn: half the time uniformly within the field's schema range (when
it has a finite one), otherwise scaled by a factor log-uniform in [1/30, 30];
one time in ten the sign is flipped. Then, in order:

1. the schema (companion.config.MfcConfig, cross-field checks included) may
   refuse it: *rejected*;
2. ``check-config --fly`` (sitl.lab.config_check) may fail it: *failed check*;
3. a config that passed both is *accepted*, and is flown on held-out flights
   the check never flies: ``train-acro`` (15 s, seed 314) on the F450 and on the
   X500, which is not one of the check's vehicles. An accepted config that
   crashes there, or whose error exceeds the shipped controller's by more than
   the check's margin, is a *violation*.

Target: no violation. Lab equipment: the product imports nothing of it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import click
import numpy as np
from pydantic import BaseModel, ValidationError

from companion.config import DEFAULT_CONTROLLER, MfcConfig, load_controller
from companion.options import SEED, WORKERS, argparse_type
from companion.profile import load_profile

ROOT = Path(__file__).resolve().parents[3]
HELD_OUT = ("f450", "x500")  # train-acro's own seed, 314
HELD_OUT_S = 15.0


def numeric_leaves(model: BaseModel, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """The paths of the float fields of a config (nested models included)."""
    paths = []
    for name in type(model).model_fields:
        value = getattr(model, name)
        path = (*prefix, name)
        if isinstance(value, BaseModel):
            paths += numeric_leaves(value, path)
        elif isinstance(value, float) and not isinstance(value, bool):
            paths.append(path)
    return paths


def _bounds(model: BaseModel, path: tuple[str, ...]) -> tuple[float, float]:
    """The schema's range of the field at ``path`` (inf where open)."""
    for name in path[:-1]:
        model = getattr(model, name)
    lo, hi = -math.inf, math.inf
    for m in type(model).model_fields[path[-1]].metadata:
        lo = getattr(m, "ge", getattr(m, "gt", lo))
        hi = getattr(m, "le", getattr(m, "lt", hi))
    return float(lo), float(hi)


def _set(doc: dict[str, Any], path: tuple[str, ...], value: float) -> None:
    for name in path[:-1]:
        doc = doc[name]
    doc[path[-1]] = value


def _get(model: BaseModel, path: tuple[str, ...]) -> float:
    obj: Any = model
    for name in path:
        obj = getattr(obj, name)
    return float(obj)


def mutants(seed: int, n: int) -> list[tuple[list[str], dict[str, Any]]]:
    """``n`` mutated config documents: (what changed, the document)."""
    base = load_controller(DEFAULT_CONTROLLER)
    assert isinstance(base, MfcConfig)
    leaves = numeric_leaves(base)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        doc = base.model_dump(mode="json")
        changes = []
        for i in rng.choice(len(leaves), size=int(rng.integers(1, 4)), replace=False):
            path = leaves[int(i)]
            lo, hi = _bounds(base, path)
            old = _get(base, path)
            if rng.random() < 0.5 and math.isfinite(lo) and math.isfinite(hi):
                value = float(rng.uniform(lo, hi))
            else:
                value = old * float(np.exp(rng.uniform(math.log(1 / 30), math.log(30))))
            if rng.random() < 0.1:
                value = -value
            _set(doc, path, value)
            changes.append(f"{'.'.join(path)}: {old:g} -> {value:.4g}")
        out.append((changes, doc))
    return out


def _held_out(cfg: MfcConfig) -> list[dict[str, Any]]:
    from sitl.lab.config_check import fly_flight
    from sitl.scenario import load_scenario

    sc = load_scenario("train-acro").model_copy(update={"duration_s": HELD_OUT_S})
    given = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    profiles = ROOT / "vehicle_profiles"
    plants = [load_profile(profiles / f"{v}.yaml", simulated=True) for v in HELD_OUT]
    return [fly_flight(plant, cfg, given, sc) for plant in plants]


def judge(job: tuple[list[str], dict[str, Any]]) -> dict[str, Any]:
    """One mutant through the schema, the check and the held-out flights."""
    from sitl.lab.config_check import check_controller, judge_flight

    changes, doc = job
    rec: dict[str, Any] = {"changes": changes}
    try:
        cfg = MfcConfig.model_validate(doc)
    except ValidationError as exc:
        rec["verdict"] = "rejected"
        rec["why"] = exc.errors()[0]["msg"][:200]
        return rec
    problems = [p for f in check_controller(cfg) for p in f.problems]
    if problems:
        rec["verdict"] = "failed_check"
        rec["why"] = problems[0]
        return rec
    flights = _held_out(cfg)
    bad = [
        p
        for v, f, s in zip(HELD_OUT, flights, _held_out_shipped(), strict=True)
        for p in judge_flight(v, f, s).problems
    ]
    rec["verdict"] = "violation" if bad else "accepted"
    rec["held_out"] = dict(zip(HELD_OUT, flights, strict=True))
    if bad:
        rec["why"] = "; ".join(bad)
    return rec


_SHIPPED: list[dict[str, Any]] = []


def _held_out_shipped() -> list[dict[str, Any]]:
    """The shipped controller on the held-out flights (once per process)."""
    if not _SHIPPED:
        cfg = load_controller(DEFAULT_CONTROLLER)
        assert isinstance(cfg, MfcConfig)
        _SHIPPED.extend(_held_out(cfg))
    return _SHIPPED


def campaign(seed: int, n: int, workers: int) -> dict[str, Any]:
    jobs = mutants(seed, n)
    if workers <= 1:
        records = [judge(j) for j in jobs]
    else:
        with ProcessPoolExecutor(workers) as pool:
            records = list(pool.map(judge, jobs))
    counts = {
        k: sum(r["verdict"] == k for r in records)
        for k in ("rejected", "failed_check", "accepted", "violation")
    }
    return {"seed": seed, "mutants": n, **counts, "target_met": counts["violation"] == 0,
            "records": records}  # fmt: skip


MAX_MUTANTS = 100_000
"""``--n``: each mutant is flown for seconds; a hundred thousand is days of flights."""


def parser() -> argparse.ArgumentParser:
    """The command line of ``scripts/fuzz.py config``."""
    ap = argparse.ArgumentParser(prog="fuzz.py config", description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=argparse_type(SEED), default=1)
    ap.add_argument(
        "--n", type=argparse_type(click.IntRange(0, MAX_MUTANTS)), default=100, help="mutants"
    )
    ap.add_argument("--workers", type=argparse_type(WORKERS), default=2)
    ap.add_argument("--json", action="store_true", help="print the report as one JSON object")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    report = campaign(args.seed, args.n, args.workers)
    if args.json:
        print(json.dumps(report))
    else:
        for r in report["records"]:
            print(f"{r['verdict']:13s} {'; '.join(r['changes'])}  {r.get('why', '')}")
        print({k: v for k, v in report.items() if k != "records"})
    return 0 if report["target_met"] else 1


if __name__ == "__main__":
    sys.exit(main())
