"""The lab's executor: a top-level function over many items on Dask ``distributed``.

One seam for every batch of flights the lab runs (``companion campaign`` today).
:class:`Executor` holds a Dask client: either a ``LocalCluster`` of worker
processes on this machine (one thread each), or a connection to a running
cluster (``dask scheduler`` and ``dask worker`` processes, the project installed
on every worker). :meth:`Executor.run` feeds it the items a few at a time (at
most twice the workers' threads in flight, more as each finishes), so a grid of
thousands of flights is never submitted at once and an iterator of items is
consumed lazily.

Failures are values. The function runs inside :func:`_guarded`, which turns an
exception into the outcome's ``error`` string; a task whose worker died is
retried elsewhere (Dask's ``retries``, and the scheduler reschedules what a
lost worker held); one that still fails is an outcome with an error too. A
batch never hangs on, nor is aborted by, one bad item.

Each item must carry all its task needs (it is pickled to the worker), and
``fn`` must be importable there (a module-level function). Local workers are
started with ``spawn``: a script that runs a batch needs the ``if __name__ ==
"__main__":`` guard.
"""

from __future__ import annotations

import logging
import os
import time
import traceback
import uuid
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sized
from dataclasses import dataclass
from typing import Any

__all__ = ["Executor", "TaskOutcome", "run_tasks"]

_log = logging.getLogger(__name__)

IN_FLIGHT_PER_THREAD = 2
"""Tasks kept submitted per worker thread: one running, one queued behind it."""
RETRIES = 2
"""Dask retries of a task whose run failed outside the function (a worker died)."""

QUIET_WORKERS = {
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.worker.memory.monitor-interval": "2s",
    "distributed.worker.profile.enabled": False,
}
"""Dask settings for the local cluster's workers. A flight is pure Python that holds
the GIL: the worker's event loop waking every 20 ms (its tick, by default), its
system and memory monitors and its statistical profiler take it from the flight.
Measured on 48 flights of 10 s on 2 cores (the flights alone, the cluster started):
17.0 s with these against 21-22 s without, the Pool's 17.0-19.3 s. A cluster's own
workers take them from their environment (docs/campaigns.md)."""


@dataclass(frozen=True)
class TaskOutcome:
    """What became of one item: the function's ``value``, or its ``error``.

    ``index`` is the item's position in the input; ``error`` is ``"Type: message
    (at file:line in function)"`` when the function raised or the task was lost.
    """

    index: int
    item: Any
    value: Any = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def _describe(exc: BaseException) -> str:
    """``Type: message (at file:line in function)``, from the innermost frame."""
    text = "".join(traceback.format_exception_only(type(exc), exc)).strip()
    frames = traceback.extract_tb(exc.__traceback__)
    if frames:
        f = frames[-1]
        text += f" (at {os.path.basename(f.filename)}:{f.lineno} in {f.name})"
    return text


def _distributed() -> Any:
    """The ``distributed`` module, imported when a cluster is wanted (untyped API)."""
    import distributed

    return distributed


def _guarded(fn: Callable[[Any], Any], item: Any) -> tuple[bool, Any]:
    """Run ``fn(item)`` on a worker: ``(True, value)``, or ``(False, error text)``."""
    try:
        return True, fn(item)
    except Exception as exc:  # a failed item is an outcome, never a failed batch
        return False, _describe(exc)


class Executor:
    """A Dask client for the lab's batches; use it as a context manager.

    Parameters
    ----------
    scheduler
        ``tcp://HOST:PORT`` of a running Dask scheduler; None starts a
        ``LocalCluster`` of ``workers`` processes on this machine.
    workers
        Local worker processes (one thread each) [default: ``os.cpu_count()``];
        ignored with ``scheduler`` (the cluster has its own).
    connect_timeout_s
        How long to wait for ``scheduler`` to answer.

    Raises
    ------
    ValueError
        On entry, when no scheduler answers at ``scheduler``.
    """

    def __init__(
        self,
        scheduler: str | None = None,
        workers: int | None = None,
        *,
        connect_timeout_s: float = 10.0,
    ) -> None:
        self.scheduler = scheduler
        self.workers = max(1, workers or os.cpu_count() or 1)
        self.connect_timeout_s = connect_timeout_s
        self._client: Any = None
        self._cluster: Any = None
        self._threads = 0
        self._threads_checked = 0.0
        self._log_level = logging.NOTSET

    def __enter__(self) -> Executor:
        dd = _distributed()
        # The scheduler of a local cluster lives in this process and logs every
        # worker's comings and goings at INFO: keep this process's stderr for the bar.
        quiet = logging.getLogger("distributed")
        self._log_level = quiet.level
        quiet.setLevel(logging.ERROR if self.scheduler is None else logging.WARNING)
        if self.scheduler is None:
            import dask

            # The workers' nannies hand the configuration in force to the workers.
            with dask.config.set(QUIET_WORKERS):
                self._cluster = self._local_cluster(dd)
            self._client = dd.Client(self._cluster)
        else:
            try:
                self._client = dd.Client(self.scheduler, timeout=f"{self.connect_timeout_s}s")
            except (OSError, TimeoutError) as exc:
                quiet.setLevel(self._log_level)
                raise ValueError(
                    f"no Dask scheduler answered at {self.scheduler} within "
                    f"{self.connect_timeout_s:g} s ({exc})"
                ) from exc
        return self

    def _local_cluster(self, dd: Any) -> Any:
        return dd.LocalCluster(
            n_workers=self.workers,
            threads_per_worker=1,
            processes=True,
            # On a free port: Dask serves its HTTP routes even with the dashboard
            # off, and a fixed port may be another cluster's.
            dashboard_address=":0",
            silence_logs=logging.ERROR,
        )

    def __exit__(self, *exc: object) -> None:
        if self._client is not None:
            self._client.close()
        if self._cluster is not None:
            self._cluster.close()
        self._client = self._cluster = None
        logging.getLogger("distributed").setLevel(self._log_level)

    @property
    def dashboard_link(self) -> str:
        """The address of Dask's dashboard for this cluster."""
        return str(self._client.dashboard_link)

    def threads(self) -> int:
        """Worker threads in the cluster now (checked at most every 2 s), at least 1."""
        now = time.monotonic()
        if self._cluster is not None:
            return self.workers
        if now - self._threads_checked > 2.0:
            self._threads = sum(self._client.nthreads().values())
            self._threads_checked = now
        return max(1, self._threads)

    def run(
        self,
        fn: Callable[[Any], Any],
        items: Iterable[Any],
        *,
        on_result: Callable[[TaskOutcome], None] | None = None,
        tally: Callable[[Any], str | None] | None = None,
        desc: str = "tasks",
        unit: str = "task",
        total: int | None = None,
        progress: bool = True,
        collect: bool = True,
    ) -> list[TaskOutcome]:
        """``fn`` over ``items`` on the cluster; the outcomes in item order.

        Parameters
        ----------
        fn
            A module-level function of one item.
        items
            Consumed lazily, as workers free up.
        on_result
            Called in this process with each outcome as it completes (in
            completion order), e.g. to store it.
        tally
            Names what a value counts as on the progress bar (``"crashed"``), or
            None; errors are counted as ``errors``.
        desc, unit, total, progress
            The tqdm bar (on stderr): its label, unit, length (default:
            ``len(items)`` when it has one) and whether it shows.
        collect
            Return the outcomes; False returns an empty list and keeps none (each
            is handed to ``on_result`` only), so a long batch holds only the
            tasks in flight.
        """
        from tqdm import tqdm

        if self._client is None:
            raise RuntimeError("Executor.run outside its `with` block")
        if total is None and isinstance(items, Sized):
            total = len(items)
        pending: Iterator[tuple[int, Any]] = enumerate(items)
        batch = uuid.uuid4().hex[:8]
        in_flight: dict[Any, tuple[int, Any]] = {}
        done: list[TaskOutcome] = []
        counts: Counter[str] = Counter()
        ac = _distributed().as_completed()

        def top_up() -> None:
            while len(in_flight) < IN_FLIGHT_PER_THREAD * self.threads():
                nxt = next(pending, None)
                if nxt is None:
                    return
                i, item = nxt
                fut = self._client.submit(
                    _guarded, fn, item, retries=RETRIES, pure=False, key=f"{desc}-{batch}-{i}"
                )
                in_flight[fut] = (i, item)
                ac.add(fut)

        with tqdm(total=total, desc=desc, unit=unit, disable=not progress) as bar:
            top_up()
            for fut in ac:
                i, item = in_flight.pop(fut)
                outcome = self._outcome(fut, i, item)
                fut.release()
                if collect:
                    done.append(outcome)
                if outcome.ok:
                    label = tally(outcome.value) if tally else None
                    if label:
                        counts[label] += 1
                else:
                    _log.warning("%s %d failed: %s", desc, i, outcome.error)
                    counts["errors"] += 1
                if counts:
                    bar.set_postfix(counts, refresh=False)
                bar.update(1)
                if on_result is not None:
                    on_result(outcome)
                top_up()
        return sorted(done, key=lambda o: o.index)

    @staticmethod
    def _outcome(fut: Any, index: int, item: Any) -> TaskOutcome:
        if fut.status == "finished":
            ok, payload = fut.result()
            return TaskOutcome(index, item, payload if ok else None, None if ok else payload)
        # Lost (its workers kept dying: KilledWorker) or cancelled: the error is Dask's.
        exc = fut.exception() if fut.status == "error" else None
        return TaskOutcome(index, item, error=_describe(exc) if exc else f"task {fut.status}")


def run_tasks(
    fn: Callable[[Any], Any],
    items: Iterable[Any],
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    **run_kw: Any,
) -> list[TaskOutcome]:
    """One batch on its own cluster: :meth:`Executor.run` inside an :class:`Executor`."""
    with Executor(scheduler, workers) as ex:
        return ex.run(fn, items, **run_kw)
