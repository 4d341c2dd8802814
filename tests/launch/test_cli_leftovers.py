"""What ``launch-swarm`` says it leaves behind is what it leaves (issue 41, point 6).

- The temporary log directory it prints is announced as removed if the run succeeds: a run
  that succeeds removes it, one that fails keeps it and says so; ``--log-dir DIR`` is always
  kept.
- ``--record DIR`` into a directory holding a recording is refused in one line (exit 2) before
  anything starts, unless ``--overwrite`` is given.
- Every drone's end action is reported, including the one whose agent was killed.

The command runs as a user runs it (``python -m swarm.launch.cli``, a non-interactive
environment), with its world and agents on emulated vehicles.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from swarm.observe.recording.reader import read_recording
from tests.helpers.cli_tools import launch_swarm_in_process, run_cli

CASE1 = "configs/case1.toml"
# The start line, as rich wraps it at 140 columns when stdout is not a terminal.
TEMPORARY_LOGS = re.compile(r"logs\s+(\S+)\s+\(removed if the run succeeds; --log-dir keeps "
                            r"them\)")


def launch(*args: str) -> subprocess.CompletedProcess[str]:
    return run_cli(CASE1, "--headless", *args, timeout=180.0)


def said(result: subprocess.CompletedProcess[str]) -> str:
    """stdout and stderr with every run of whitespace as one space (rich wraps long lines)."""
    return " ".join((result.stdout + result.stderr).split())


def temporary_log_dir(result: subprocess.CompletedProcess[str]) -> Path:
    match = TEMPORARY_LOGS.search(result.stdout)
    assert match is not None, result.stdout
    return Path(match.group(1))


def test_a_recording_is_replaced_only_when_asked_and_a_good_run_removes_its_logs(
        tmp_path: Path) -> None:
    record = tmp_path / "rec"
    first = launch("--duration", "2", "--record", str(record))
    assert first.returncode == 0, said(first)
    assert not temporary_log_dir(first).exists()  # the run succeeded: gone, as announced
    recording = (record / "run.mcap").read_bytes()

    again = launch("--duration", "2", "--record", str(record))
    assert again.returncode == 2, said(again)
    assert again.stdout == ""  # not even the launcher's first line: nothing started
    assert again.stderr.splitlines() == [
        f"launch-swarm: --record {record}: {record / 'run.mcap'} holds a recording already; "
        f"record to another directory, or add --overwrite to replace it"]
    assert (record / "run.mcap").read_bytes() == recording

    replaced = launch("--duration", "2", "--record", str(record), "--overwrite", "--seed", "3")
    assert replaced.returncode == 0, said(replaced)
    assert read_recording(record).record.seed == 3
    assert not temporary_log_dir(replaced).exists()


@pytest.mark.parametrize(("args", "line"), [
    (["--inprocess", "--record", "{record}"],
     "launch-swarm: --record {record}: {record}/run.mcap holds a recording already; record to "
     "another directory, or add --overwrite to replace it"),
    (["--overwrite"],
     "launch-swarm: --overwrite needs --record DIR (it replaces the recording in DIR)"),
], ids=["inprocess_into_a_recording", "overwrite_without_record"])
def test_record_options_that_would_lose_a_recording_exit_2_with_one_line(
        tmp_path: Path, args: list[str], line: str) -> None:
    record = tmp_path / "rec"
    record.mkdir()
    (record / "run.mcap").write_bytes(b"an earlier run")
    result = launch_swarm_in_process(CASE1, "--headless", "--duration", "2",
                                     *[a.format(record=record) for a in args])
    assert (result.returncode, result.stdout) == (2, ""), said(result)
    assert result.stderr.splitlines() == [line.format(record=record)]
    assert (record / "run.mcap").read_bytes() == b"an earlier run"


def test_a_log_dir_given_is_kept_and_not_announced_as_removed(tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    result = launch("--duration", "1.5", "--log-dir", str(logs))
    assert result.returncode == 0, said(result)
    assert f"logs {logs}" in said(result) and "removed" not in result.stdout
    assert sorted(p.name for p in logs.glob("*.log")) == [
        *(f"agent{i}.log" for i in range(6)), "world.log"]


@pytest.mark.wallclock
def test_a_run_that_fails_keeps_its_logs_says_so_and_reports_every_end_action() -> None:
    """Realtime, drone 2's agent killed at t = 2 s: the mission goes on, the run fails (exit
    1), the logs stay where the first line said, and every drone's end action is reported —
    the killed agent's was never sent."""
    result = launch("--mode", "realtime", "--duration", "5", "--kill-agent", "2@2")
    logs = temporary_log_dir(result)
    try:
        assert result.returncode == 1, said(result)
        text = said(result)
        assert f"launch-swarm: the run did not succeed: logs kept in {logs}" in text
        # The loss quoted this log: it is still there to read.
        assert f"last lines of {logs / 'agent2.log'}" in text
        assert "drone 2: armed and streaming" in (logs / "agent2.log").read_text()
        assert "launch-swarm: drones 0, 1, 3, 4, 5: end action hold (Hold) accepted" in text
        assert ("launch-swarm: drone 2: end action hold (Hold) not sent: its agent ended with "
                "signal 9 before it could send it; the vehicle is left to its own "
                "setpoint-loss failsafe") in text
    finally:
        shutil.rmtree(logs, ignore_errors=True)
