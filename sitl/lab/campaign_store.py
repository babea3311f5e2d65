"""A campaign's folder as it runs: one file per finished flight, so a run resumes.

Layout in ``--out``
-------------------
``campaign-run.json``
    The manifest, written when a run starts: the grid's digest and size.
``flights/<flight id>.json``
    One flight's record, written (atomically: a temporary file, then
    ``os.replace``) in the client as the flight completes.
``oracle/<case id>.json``
    One case's feasibility verdict (whether the oracle that may also set the
    collective crashes in it), stored the same way.
``limit/<case id>.json``
    One case's oracle flight (its MAE per axis: the limit the case's flights are
    read against), stored the same way.

Identities
----------
A flight's id is a digest of everything that decides it: the profile's name and
content (damage included), the damage, gust and seed, the controller's name and
content, the scenario's content (wind, duration, link included) and the
duration. A changed configuration gives new ids, so a stale record is never
reused. A case's id is the same without the controller. The grid's digest is
that of the code (:func:`code_digest`) and its flight ids in order: a run of
other code is another grid's, so records flown by two versions never mix.

Resuming
--------
A run may resume a folder whose manifest names the same grid and that has no
``campaign.json`` yet (:func:`can_resume`): the flights whose records exist are
not flown again, except those that raised (their records keep the ``error``
until a run flies them). A finished run, or another grid's, is moved aside instead
(the command's ``earlier-<UTC time>/``). Records are written by the one client
process, so a flight is stored once; one in flight when the client died is
flown again by the next run.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
from collections.abc import Callable, Iterable, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sitl.lab.atomic import replacing, write_json_atomic

if TYPE_CHECKING:
    from sitl.lab.campaign_spec import FlightSpec

__all__ = [
    "FLIGHTS_DIR",
    "LIMIT_DIR",
    "MANIFEST",
    "ORACLE_DIR",
    "RUN_FILES",
    "CampaignStore",
    "can_resume",
    "case_ids",
    "code_digest",
    "flight_ids",
    "grid_digest",
    "replacing",
    "sources_digest",
    "write_json_atomic",
]

_log = logging.getLogger(__name__)

MANIFEST = "campaign-run.json"
FLIGHTS_DIR = "flights"
ORACLE_DIR = "oracle"
LIMIT_DIR = "limit"
RUN_FILES = (MANIFEST, FLIGHTS_DIR, ORACLE_DIR, LIMIT_DIR)
"""What a run keeps in its folder besides the final outputs."""
FINISHED_MARK = "campaign.json"
"""The final output written last: present, the run is finished."""


def _digest(obj: Any) -> str:
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


class _Contents:
    """Digests of the pydantic models a grid shares, each computed once."""

    def __init__(self) -> None:
        self._seen: dict[int, tuple[Any, str]] = {}

    def __call__(self, model: Any) -> str:
        hit = self._seen.get(id(model))
        if hit is None or hit[0] is not model:
            hit = (model, _digest(model.model_dump(mode="json")))
            self._seen[id(model)] = hit
        return hit[1]


def _case_key(spec: FlightSpec, contents: _Contents) -> dict[str, Any]:
    return {
        "profile": spec.profile_name,
        "profile_content": contents(spec.profile),
        "damage": spec.damage,
        "gust_sigma_m_s": spec.gust_sigma_m_s,
        "seed": spec.seed,
        "scenario_content": contents(spec.scenario),
        "duration_s": spec.scenario.duration_s,
    }


def flight_ids(specs: Iterable[FlightSpec]) -> list[str]:
    """Each spec's flight id (20 hex digits), in order."""
    contents = _Contents()
    return [
        _digest(
            {
                **_case_key(s, contents),
                "controller": s.controller_name,
                "controller_content": contents(s.controller),
            }
        )[:20]
        for s in specs
    ]


def case_ids(specs: Iterable[FlightSpec]) -> list[str]:
    """Each spec's case id (its flight's id without the controller), in order."""
    contents = _Contents()
    return [_digest(_case_key(s, contents))[:20] for s in specs]


@functools.cache
def code_digest() -> str:
    """A digest of the code that flies and scores the flights: every Python source
    of the ``companion`` and ``sitl`` packages (as installed)."""
    import companion
    import sitl

    return sources_digest(
        (pkg.__name__, Path(str(pkg.__file__)).resolve().parent) for pkg in (companion, sitl)
    )


def sources_digest(packages: Iterable[tuple[str, Path]]) -> str:
    """A digest of the ``*.py`` files under each ``(name, folder)``, by name and
    relative path (20 hex digits)."""
    h = hashlib.sha256()
    for name, root in packages:
        for path in sorted(root.rglob("*.py")):
            h.update(f"{name}/{path.relative_to(root).as_posix()}\n".encode())
            h.update(hashlib.sha256(path.read_bytes()).digest())
    return h.hexdigest()[:20]


def grid_digest(ids: Sequence[str]) -> str:
    """The grid's identity: a digest of the code (:func:`code_digest`) and its
    flight ids in order."""
    return hashlib.sha256("\n".join([code_digest(), *ids]).encode("ascii")).hexdigest()[:20]


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        _log.warning("%s: unreadable (%s); it is redone", path, exc)
        return None


def can_resume(
    folder: Path, grid: str, manifest: str = MANIFEST, finished: str = FINISHED_MARK
) -> bool:
    """Whether ``folder`` holds an unfinished run of the grid ``grid`` (module docstring):
    its ``manifest`` names ``grid`` and its ``finished`` output is not there yet."""
    doc = _read_json(folder / manifest)
    return isinstance(doc, dict) and doc.get("grid") == grid and not (folder / finished).exists()


class CampaignStore:
    """The per-flight and per-case records of one run in ``folder`` (module docstring).

    ``manifest`` and ``finished`` name the run's manifest and the output written
    last (a campaign's by default; the envelope keeps its own)."""

    def __init__(
        self, folder: str | Path, manifest: str = MANIFEST, finished: str = FINISHED_MARK
    ) -> None:
        self.folder = Path(folder)
        self.manifest = manifest
        self.finished = finished

    def can_resume(self, grid: str) -> bool:
        """Whether the folder holds an unfinished run of ``grid``."""
        return can_resume(self.folder, grid, self.manifest, self.finished)

    def start(self, grid: str, flights: int) -> None:
        """Write the manifest (kept as it is when resuming the same grid)."""
        if self.can_resume(grid):
            return
        started = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
        write_json_atomic(
            self.folder / self.manifest, {"grid": grid, "flights": flights, "started_utc": started}
        )

    def load(self, sub: str, ids: Iterable[str]) -> dict[str, Any]:
        """The stored records in ``sub/`` among ``ids`` that have no ``error``, by id."""
        return self._load(sub, ids)

    def save(self, sub: str, key: str, record: dict[str, Any]) -> None:
        """Store ``record`` as ``sub/<key>.json``, whole or not at all."""
        write_json_atomic(self.folder / sub / f"{key}.json", record)

    def run_missing(
        self,
        sub: str,
        keys: Sequence[str],
        fn: Callable[[Any], dict[str, Any]],
        items: Sequence[Any],
        **run_kw: Any,
    ) -> tuple[dict[str, Any], list[Any]]:
        """Run ``fn`` (on the lab's executor, :func:`sitl.lab.executor.run_tasks` with
        ``run_kw``) on those of ``items`` whose key has no record in ``sub/`` yet,
        storing each value as it lands.

        Returns the records by key (stored before and new) and the new tasks'
        outcomes (their ``item`` says which; one that raised has no record)."""
        from sitl.lab.executor import TaskOutcome, run_tasks

        done = self.load(sub, keys)
        todo = [i for i, k in enumerate(keys) if k not in done]

        def keep(o: TaskOutcome) -> None:
            if o.ok:
                key = keys[todo[o.index]]
                self.save(sub, key, o.value)
                done[key] = o.value

        if not todo:
            return done, []
        outcomes = run_tasks(fn, [items[i] for i in todo], on_result=keep, **run_kw)
        return done, outcomes

    def _load(self, sub: str, ids: Iterable[str]) -> dict[str, Any]:
        """The stored records among ``ids`` that have no ``error``, by id."""
        d = self.folder / sub
        if not d.is_dir():
            return {}
        out = {}
        for i in ids:
            rec = _read_json(d / f"{i}.json")
            if isinstance(rec, dict) and rec.get("error") is None:
                out[i] = rec
        return out

    def flights(self, ids: Iterable[str]) -> dict[str, dict[str, Any]]:
        """The finished flights among ``ids``, by flight id. One that raised (its
        record has an ``error``) is not finished: a resumed run flies it again."""
        return self._load(FLIGHTS_DIR, ids)

    def save_flight(self, flight_id: str, record: dict[str, Any]) -> None:
        write_json_atomic(self.folder / FLIGHTS_DIR / f"{flight_id}.json", record)

    def verdicts(self, ids: Iterable[str]) -> dict[str, dict[str, Any]]:
        """The stored oracle verdicts among ``ids``, by case id (as for flights, one
        whose oracle flight raised is asked again)."""
        return self._load(ORACLE_DIR, ids)

    def save_verdict(self, case_id: str, verdict: dict[str, Any]) -> None:
        write_json_atomic(self.folder / ORACLE_DIR / f"{case_id}.json", verdict)

    def limits(self, ids: Iterable[str]) -> dict[str, dict[str, Any]]:
        """The stored oracle flights among ``ids``, by case id (one that raised is
        flown again)."""
        return self._load(LIMIT_DIR, ids)

    def save_limit(self, case_id: str, limit: dict[str, Any]) -> None:
        write_json_atomic(self.folder / LIMIT_DIR / f"{case_id}.json", limit)
