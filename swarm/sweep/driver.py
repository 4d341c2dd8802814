"""The sweep on Dask distributed: a local cluster by default, or the scheduler given.

Every point not yet in ``results.jsonl`` becomes one Dask task (``run_mission``), keyed by the
point's key and retried by Dask when it raises (``RETRIES``); a worker lost mid-mission has
its tasks run again on another worker (the scheduler's own rule, up to
``distributed.scheduler.allowed-failures`` deaths, then a ``KilledWorker`` error: a FAILED row
with that reason). Results reach this process only: it writes each row as it arrives and never
a key twice.

Ctrl-C (SIGINT, or SIGTERM): the first sets the sweep's Dask Event, which every running
mission polls (``swarm.sweep.missions``): each stops its launch-swarm (its world and agents)
or its in-process loop; the pending tasks are cancelled, and the local cluster, if ours, is
closed (its worker processes end, and with them anything they started). No row is written
for a mission that was stopped: a rerun runs it. A second Ctrl-C leaves at once.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from swarm.errors import UsageError
from swarm.sweep.missions import STOPPED, run_mission
from swarm.sweep.plan import SweepPlan
from swarm.sweep.results import ResultsWriter
from swarm.sweep.rows import FAILED, OK, MissionTask, failed_row

RETRIES = 2  # Dask reruns a task that raised this many times
POLL_S = 0.25  # the client's loop: results, progress, Ctrl-C [s]
STOP_GRACE_S = 30.0  # after Ctrl-C, how long running missions get to stop [s]
CONNECT_TIMEOUT_S = 15.0


class SchedulerError(UsageError, RuntimeError):
    """The scheduler given (``--scheduler``) cannot be reached; one line."""


@dataclass
class Outcome:
    written: int = 0
    ok: int = 0
    failed: int = 0
    interrupted: bool = False
    dashboard: str | None = None
    rows: list[dict[str, Any]] = field(default_factory=list)


@contextlib.contextmanager
def _interrupts() -> Iterator[list[int]]:
    """SIGINT and SIGTERM counted instead of raised (the loop looks at the count); a second
    one raises KeyboardInterrupt at once."""
    count = [0]

    def handler(_signum: int, _frame: object) -> None:
        count[0] += 1
        if count[0] > 1:
            raise KeyboardInterrupt

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield count
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while the local cluster starts: its worker processes inherit that
    (spawned Pythons leave an ignored SIGINT ignored), so a terminal's Ctrl-C reaches this
    process only, which stops the sweep in order instead of every worker dying mid-task."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def dask_client(scheduler: str | None, workers: int) -> Iterator[Any]:
    """A Dask client: of a new local cluster of ``workers`` processes with one thread each,
    or of the scheduler at ``scheduler`` (tcp://HOST:PORT)."""
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as err:
            raise SchedulerError(f"--scheduler {scheduler}: cannot connect: {err}") from None
        try:
            yield client
        finally:
            client.close()
        return
    with _sigint_ignored():
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=":0", silence_logs=logging.ERROR)
        client = Client(cluster)
    try:
        yield client
    finally:
        with contextlib.suppress(Exception):
            client.close()
        with contextlib.suppress(Exception):
            cluster.close()


def _running(client: Any) -> int:
    """Tasks processing on the workers, at most one per worker thread."""
    try:
        processing = client.processing()
        threads = client.nthreads()
    except Exception:  # the scheduler busy or gone: the count is only for the display
        return 0
    return sum(min(len(keys), threads.get(worker, 1)) for worker, keys in processing.items())


def run_sweep(plan: SweepPlan, writer: ResultsWriter, console: Console, *,
              scheduler: str | None, workers: int, stop_event: str) -> Outcome:
    """Run every task of ``plan`` whose key ``writer`` does not hold yet."""
    from distributed import Event, wait

    todo = [t for t in plan.tasks if t.key not in writer.keys]
    outcome = Outcome()
    if not todo:
        return outcome
    with _interrupts() as interrupts, dask_client(scheduler, workers) as client:
        outcome.dashboard = client.dashboard_link
        console.print(f"Dask dashboard: {client.dashboard_link}", highlight=False)
        event = Event(stop_event, client=client)
        event.clear()
        futures = {}
        for task in todo:
            future = client.submit(run_mission, task, key=f"vigil-mission-{task.key}",
                                   retries=RETRIES, pure=False)
            futures[future] = task
        pending = set(futures)
        stop_deadline: float | None = None
        with _progress(console) as progress:
            bar = progress.add_task("missions", total=len(todo), failed=0, running=0)
            last_count = 0.0
            while pending:
                if interrupts[0] and stop_deadline is None:
                    stop_deadline = time.monotonic() + STOP_GRACE_S
                    outcome.interrupted = True
                    progress.console.print(
                        f"interrupted: stopping the {len(pending)} missions not finished; "
                        f"their points run on the next run of the same command",
                        highlight=False)
                    _stop(client, event, pending)
                if stop_deadline is not None and time.monotonic() > stop_deadline:
                    client.cancel(list(pending))
                    break
                with contextlib.suppress(TimeoutError):  # none finished within POLL_S
                    wait(list(pending), timeout=POLL_S, return_when="FIRST_COMPLETED")
                for future in [f for f in pending if f.done()]:
                    pending.discard(future)
                    row = _row(future, futures[future])
                    if row is None or (stop_deadline is not None
                                       and row["reason"].startswith(STOPPED)):
                        continue
                    if writer.write(row):
                        outcome.written += 1
                        outcome.rows.append(row)
                        outcome.ok += row["verdict"] == OK
                        outcome.failed += row["verdict"] == FAILED
                    _log_row(progress, row)
                    progress.update(bar, advance=1, failed=outcome.failed)
                now = time.monotonic()
                if now - last_count > 1.0:
                    last_count = now
                    progress.update(bar, running=_running(client))
            progress.update(bar, running=0)
    return outcome


def _stop(client: Any, event: Any, pending: set[Any]) -> None:
    """Set the stop Event (the running missions stop, and return at once if they start
    later) and cancel the tasks no worker has started."""
    event.set()
    try:
        busy = {k for keys in client.processing().values() for k in keys}
    except Exception:  # the scheduler gone: nothing runs any more
        busy = set()
    idle = [f for f in pending if f.key not in busy]
    client.cancel(idle)
    pending.difference_update(idle)


def _row(future: Any, task: MissionTask) -> dict[str, Any] | None:
    """The row a finished future stands for: its result, a FAILED row for an error (a worker
    lost too often, a task that raised on every try), None when it was cancelled."""
    if future.status == "finished":
        return future.result()
    if future.status == "error":
        error = future.exception()
        return failed_row(task, f"{type(error).__name__}: {error}")
    return None


def _log_row(progress: Progress, row: dict[str, Any]) -> None:
    params = " ".join(f"{k}={v}" for k, v in row["params"].items())
    margin = row.get("min_lambda_margin")
    shown = "—" if margin is None else f"{margin:+.4f}"
    line = (f"{row['verdict']:<8} {params} seed {row['seed']}  min λ̄−ε {shown}  "
            f"{row['wall_s']:.1f} s")
    if row["verdict"] != OK and row.get("reason"):
        line += f"  ({row['reason'][:160]})"
    progress.console.print(line, highlight=False, markup=False)


def _progress(console: Console) -> Progress:
    return Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("failed {task.fields[failed]}"), TextColumn("running {task.fields[running]}"),
        TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), console=console,
        transient=False)


def new_stop_event() -> str:
    return f"vigil-sweep-stop-{uuid.uuid4().hex[:12]}"
