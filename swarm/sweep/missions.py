"""One mission of a sweep, run where Dask put it: the task function of every worker.

``inprocess``: the reference runner in the worker's task thread (``run_reference``; recorded
with ``record_reference`` when the sweep keeps recordings), its report built as launch-swarm
builds it. The other modes run the real ``launch-swarm`` in a subprocess, with its own run id,
temporary log directory and recording (read back with ``read_recording``, the figures of
``swarm-report``, and the vehicles' tracking and the survivors of a loss:
``swarm.sweep.measures``), and the MAVLink port block the launcher reserves itself (a lock file per
block: concurrent launchers on one host take different blocks).

Dask workers are daemonic processes, which may not have multiprocessing children; a subprocess
is fine. ``launch-swarm`` runs in a session of its own (a terminal's Ctrl-C reaches the sweep
command, which stops it) and dies with the worker's task thread (``PR_SET_PDEATHSIG``, as the
launcher's own children die with it): a worker killed with ``kill -9`` leaves no mission
behind. A stop (the sweep interrupted: its Dask Event set) or the mission's timeout sends it
SIGTERM (it stops its world and agents, as on Ctrl-C), then SIGKILL after a grace period.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from swarm.children import code_path, die_with_parent
from swarm.errors import VigilError
from swarm.observe.recording.reader import read_recording
from swarm.observe.recording.schema import RECORDING_FILE
from swarm.observe.recording.writer import record_reference
from swarm.observe.report import build_report
from swarm.observe.report_cli import report_from_recording
from swarm.runs.reference import run_reference
from swarm.scenario.config import config_from_dict, write_resolved_config
from swarm.sweep.measures import recording_measures
from swarm.sweep.rows import MissionTask, failed_row, report_row

STOP_POLL_S = 0.5  # how often a mission asks whether the sweep was stopped [s]
TERM_GRACE_S = 15.0  # SIGTERM → SIGKILL of a stopped launch-swarm [s]
STOPPED = "stopped:"  # how the reason of a mission stopped by the sweep begins
LOGS = "logs"  # a process mission's log directory (kept in its recording's, if kept)
LAUNCHER_OUTPUT = "launch-swarm.log"  # its launch-swarm's stdout and stderr, if kept


class MissionStopped(VigilError):
    """The sweep was stopped, or the mission ran past its timeout."""


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def stop_check(task: MissionTask, started: float) -> Callable[[], str | None]:
    """A function saying why the mission must stop now (None: go on), cheap to call often:
    the Dask Event is asked at most every ``STOP_POLL_S``."""
    event = None
    if task.stop_event is not None:
        from distributed import Event  # a worker's client, made on first use

        event = Event(task.stop_event)
    last = [0.0]

    def check() -> str | None:
        now = time.monotonic()
        if task.timeout_s is not None and now - started > task.timeout_s:
            return f"timeout: still running after {task.timeout_s:g} s"
        if event is not None and (not last[0] or now - last[0] >= STOP_POLL_S):
            last[0] = now
            if event.is_set():
                return f"{STOPPED} the sweep was interrupted"
        return None

    return check


def run_mission(task: MissionTask) -> dict[str, Any]:
    """Run one point and return its row; a mission that fails is a FAILED row with its
    reason, never an exception (an exception here is a bug or a lost worker: Dask retries)."""
    started = time.monotonic()
    check = stop_check(task, started)
    try:
        if task.mode == "inprocess":
            return _run_inprocess(task, check, started)
        return _run_launcher(task, check, started)
    except MissionStopped as err:
        return failed_row(task, str(err), wall_s=time.monotonic() - started,
                          worker=worker_name())
    except (VigilError, OSError, ValueError) as err:
        return failed_row(task, f"{type(err).__name__}: {err}",
                          wall_s=time.monotonic() - started, worker=worker_name())


def _run_inprocess(task: MissionTask, check: Callable[[], str | None],
                   started: float) -> dict[str, Any]:
    config = config_from_dict(dict(task.config_data), source=task.source)

    def on_step(_step: int, _diagnostics: object) -> None:
        reason = check()
        if reason is not None:
            raise MissionStopped(reason)

    if task.record_dir is None:
        record = run_reference(config, task.seed, on_step=on_step)
    else:
        record = record_reference(config, task.seed, Path(task.record_dir), on_step=on_step)
    report = build_report(record, "inprocess")
    return report_row(task, report, exit_code=report.exit_code,
                      wall_s=time.monotonic() - started, worker=worker_name(),
                      recording=task.record_dir)


def launcher_argv(task: MissionTask, config_path: Path, log_dir: Path, record_dir: Path
                  ) -> list[str]:
    """``launch-swarm`` for one point (the resolved config, its seed, mode and run id)."""
    mode = "realtime" if task.mode.startswith("sitl:") else task.mode
    argv = [sys.executable, "-m", "swarm.launch.cli", str(config_path), "--headless",
            "--mode", mode, "--seed", str(task.seed), "--run-id", f"sweep-{task.key[:16]}",
            "--log-dir", str(log_dir), "--record", str(record_dir), "--overwrite"]
    if task.mode.startswith("sitl:"):
        argv += ["--sitl", task.mode.partition(":")[2]]
    for drone, time_s in task.kill_agents:
        argv += ["--kill-agent", f"{drone}@{time_s:g}"]
    return argv


def _run_launcher(task: MissionTask, check: Callable[[], str | None],
                  started: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix=f"vigil-sweep-{task.key[:12]}-") as name:
        work = Path(name)
        config = config_from_dict(dict(task.config_data), source=task.source)
        config_path = write_resolved_config(config, work / "config.json")
        # A kept recording keeps the mission's logs and launch-swarm's output beside it.
        record_dir = Path(task.record_dir) if task.record_dir else work / "recording"
        log_dir = record_dir / LOGS if task.record_dir else work / LOGS
        argv = launcher_argv(task, config_path, log_dir, record_dir)
        env = os.environ | code_path(os.environ) | {"OPENBLAS_NUM_THREADS": "1"}
        with (work / "stdout.txt").open("wb") as out, (work / "stderr.txt").open("wb") as err:
            process = subprocess.Popen(
                argv, stdin=subprocess.DEVNULL, stdout=out, stderr=err, env=env,
                start_new_session=True, preexec_fn=die_with_parent)
            stopped = _wait(process, check)
        stderr = (work / "stderr.txt").read_text(errors="replace")
        if task.record_dir:
            record_dir.mkdir(parents=True, exist_ok=True)
            (record_dir / LAUNCHER_OUTPUT).write_text(
                (work / "stdout.txt").read_text(errors="replace") + stderr)
        wall_s = time.monotonic() - started
        if stopped is not None:
            return failed_row(task, stopped, exit_code=process.returncode, wall_s=wall_s,
                              worker=worker_name())
        reason = _last_line(stderr)
        if not (record_dir / RECORDING_FILE).exists():
            return failed_row(task, reason or f"launch-swarm exited {process.returncode} "
                                              f"without a recording",
                              exit_code=process.returncode, wall_s=wall_s, worker=worker_name())
        recording = read_recording(record_dir)
        report = report_from_recording(recording)
        measures = recording_measures(recording, [drone for drone, _t in task.kill_agents])
        return report_row(task, report, exit_code=process.returncode, wall_s=wall_s,
                          reason=reason if process.returncode else "", worker=worker_name(),
                          recording=task.record_dir, measures=measures)


def _wait(process: subprocess.Popen[bytes], check: Callable[[], str | None]) -> str | None:
    """Wait for ``process``; stop its group when ``check`` says so (that reason returned)."""
    try:
        while True:
            try:
                process.wait(timeout=0.1)
                return None
            except subprocess.TimeoutExpired:
                pass
            reason = check()
            if reason is not None:
                stop_group(process)
                return reason
    except BaseException:
        stop_group(process)
        raise


def stop_group(process: subprocess.Popen[bytes]) -> None:
    """SIGTERM to the launcher's session (it stops its world and agents), SIGKILL to what is
    left after ``TERM_GRACE_S``."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGTERM)
    with contextlib.suppress(subprocess.TimeoutExpired):
        process.wait(timeout=TERM_GRACE_S)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGKILL)
    process.wait()


def _last_line(text: str) -> str:
    """The last line of launch-swarm's stderr that says something (its one-line errors)."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[-1] if lines else ""
