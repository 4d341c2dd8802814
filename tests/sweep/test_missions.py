"""One mission of a sweep as a worker runs it (swarm.sweep.missions): process missions through
the real launch-swarm, a failure as a row with its reason, a timeout that stops every process."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import psutil
import pytest

from swarm.observe.recording.schema import RECORDING_FILE
from swarm.scenario.config import config_to_data, load_config
from swarm.sweep.missions import run_mission
from swarm.sweep.plan import CODE_VERSION_VARIABLE, code_version, plan_sweep
from swarm.sweep.results import RESULTS_FILE, read_rows
from swarm.sweep.rows import MissionTask
from tests.helpers.cli_tools import ROOT, cli_env

CASE1 = ROOT / "configs" / "case1.toml"


@pytest.fixture(autouse=True)
def pinned_version(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(CODE_VERSION_VARIABLE, "test-version")
    code_version.cache_clear()


def mission_processes(run_id: str) -> list[psutil.Process]:
    """Every process whose command line names ``run_id`` (the launcher, world, agents)."""
    found = []
    for process in psutil.process_iter(["cmdline"]):
        if any(run_id in part for part in process.info["cmdline"] or ()):
            found.append(process)
    return found


def test_a_lockstep_sweep_runs_launch_swarm_and_keeps_recordings_when_asked(
        tmp_path: Path) -> None:
    sweep = tmp_path / "lockstep.toml"
    sweep.write_text(f'base = "{CASE1}"\nmode = "lockstep"\nseeds = [3, 4]\nrecord = true\n'
                     f'[set]\n"scenario.duration_s" = 1.5\n')
    out = tmp_path / "out"
    result = subprocess.run([sys.executable, "-m", "swarm.sweep.cli", str(sweep), "--out",
                             str(out), "--workers", "2"], cwd=ROOT,
                            env=cli_env(**{CODE_VERSION_VARIABLE: "test-version"}),
                            capture_output=True, text=True, timeout=240, check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    rows = read_rows(out / RESULTS_FILE)
    assert sorted(r["seed"] for r in rows) == [3, 4]
    plan = plan_sweep(sweep, out)
    for row in rows:
        assert row["mode"] == "lockstep" and row["verdict"] == "OK" and row["exit_code"] == 0
        assert row["late_steps"] == 0 and row["rejected_messages"] == 0  # agents' counters
        assert row["steps"] == row["planned_steps"] == 75
        assert Path(row["recording"], RECORDING_FILE).is_file()
        assert not mission_processes(f"sweep-{row['key'][:16]}")
    assert {r["key"] for r in rows} == {t.key for t in plan.tasks}


def task_for(mode: str, *, duration_s: float, **changes: object) -> MissionTask:
    config = load_config(CASE1).with_duration(duration_s)
    base = MissionTask(key=f"t{abs(hash((mode, duration_s, repr(changes)))):019d}"[:20],
                       params={}, axes=(), seed=0, mode=mode, config_data=config_to_data(config),
                       source=str(CASE1), code_version="test")
    return dataclasses.replace(base, **changes)


def test_a_mission_past_its_timeout_is_failed_and_leaves_no_process() -> None:
    task = task_for("lockstep", duration_s=60.0, timeout_s=4.0)
    row = run_mission(task)
    assert row["verdict"] == "FAILED"
    assert row["reason"] == "timeout: still running after 4 s"
    assert 4.0 <= row["wall_s"] < 25.0
    assert not mission_processes(f"sweep-{task.key[:16]}")


def test_a_launcher_that_refuses_is_a_failed_row_with_its_line() -> None:
    """A point no sweep file can make (a kill in lockstep): launch-swarm's own one-line
    refusal is the row's reason."""
    row = run_mission(task_for("lockstep", duration_s=2.0, kill_agents=((1, 1.0),)))
    assert row["verdict"] == "FAILED" and row["exit_code"] == 2
    assert row["reason"] == ("launch-swarm: --kill-agent needs --mode realtime (in lockstep "
                             "every drone waits for every other one)")
    assert row["min_lambda_margin"] is None


def test_an_in_process_mission_past_its_timeout_stops_between_steps() -> None:
    row = run_mission(task_for("inprocess", duration_s=600.0, timeout_s=0.5))
    assert row["verdict"] == "FAILED" and row["reason"].startswith("timeout")
    assert row["wall_s"] < 5.0
