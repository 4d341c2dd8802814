"""Sweeps on the real engine (swarm.sweep.driver): a local Dask cluster, a scheduler and two
workers over TCP with one killed, Ctrl-C and resume, the same sweep twice."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from swarm.sweep.plan import CODE_VERSION_VARIABLE, code_version, plan_sweep
from swarm.sweep.results import RESULTS_FILE, read_rows
from swarm.sweep.rows import REQUIRED_KEYS, VARYING_KEYS
from swarm.sweep.summary import HEATMAP_FILE, MARGINS_FILE, SUMMARY_FILE
from tests.helpers.cli_tools import ROOT, cli_env
from tests.helpers.process_tools import console_script, free_tcp_port

CASE1 = ROOT / "configs" / "case1.toml"
SWEEP = [sys.executable, "-m", "swarm.sweep.cli"]
# Others commit to this tree while the tests run: the keys use a pinned version, so a rerun
# is the same sweep (what a commit between two runs does to the keys: test_spec).
VERSION = {CODE_VERSION_VARIABLE: "test-version"}


@pytest.fixture(autouse=True)
def pinned_version(monkeypatch: pytest.MonkeyPatch) -> None:
    """plan_sweep here keys the points as the sweep command does."""
    monkeypatch.setenv(CODE_VERSION_VARIABLE, VERSION[CODE_VERSION_VARIABLE])
    code_version.cache_clear()


def write_sweep(directory: Path, *, seeds: tuple[int, int], duration_s: float,
                axes: str = "") -> Path:
    path = directory / "sweep.toml"
    path.write_text(f'base = "{CASE1}"\nseeds = [{seeds[0]}, {seeds[1]}]\n'
                    f'[set]\n"scenario.duration_s" = {duration_s}\n[axes]\n{axes}')
    return path


AXES = ('"gramian.epsilon" = [0.04, 0.06]\n'
        '"targets.0.velocity_m_s" = [[0.2, 0.0, 0.0], [0.6, 0.0, 0.0]]\n')


def sweep(*args: str | Path, timeout: float = 180.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*SWEEP, *map(str, args)], cwd=ROOT, env=cli_env(**VERSION),
                          capture_output=True, text=True, timeout=timeout, check=False)


def rows_of(out: Path) -> list[dict]:
    return read_rows(out / RESULTS_FILE)


@pytest.fixture(scope="module")
def local_sweep(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path,
                                                                    subprocess.CompletedProcess]:
    """2 × 2 grid × 2 seeds of 2-s Case 1 missions, in-process, on a local cluster of 2."""
    directory = tmp_path_factory.mktemp("local")
    path = write_sweep(directory, seeds=(0, 1), duration_s=2.0, axes=AXES)
    out = directory / "out"
    return path, out, sweep(path, "--out", out, "--workers", "2")


def test_local_cluster_sweep_writes_a_row_per_point_and_the_answer(
        local_sweep: tuple[Path, Path, subprocess.CompletedProcess]) -> None:
    path, out, result = local_sweep
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Dask dashboard: http://" in result.stdout
    rows = rows_of(out)
    plan = plan_sweep(path, out)
    assert sorted(r["key"] for r in rows) == sorted(t.key for t in plan.tasks)
    assert len(rows) == 8
    for row in rows:
        assert set(REQUIRED_KEYS) <= set(row)
        assert row["verdict"] == "OK" and row["exit_code"] == 0 and row["mode"] == "inprocess"
        assert row["min_lambda_margin"] > 0 and row["min_distance_m"] > 0.5
        assert set(row["params"]) == {"gramian.epsilon", "targets.0.velocity_m_s"}
        assert row["margins"]["collision_m"] == pytest.approx(row["min_distance_m"] - 0.5)
    for name in (SUMMARY_FILE, HEATMAP_FILE, MARGINS_FILE):
        assert (out / name).stat().st_size > 0
    cells = json.loads((out / SUMMARY_FILE).read_text())
    assert len(cells) == 4 and all(c["missions"] == 2 and c["ok"] == 2 for c in cells)
    assert cells[0]["wilson_95"] == pytest.approx([0.3423802, 1.0], abs=1e-6)
    assert "0.04 targets.0.velocity_m_s=[0.2, 0, 0]" in result.stdout  # the per-cell table


def test_report_redraws_from_the_results_alone(
        local_sweep: tuple[Path, Path, subprocess.CompletedProcess], tmp_path: Path) -> None:
    _path, out, _result = local_sweep
    copy = tmp_path / "copy"
    copy.mkdir()
    (copy / RESULTS_FILE).write_bytes((out / RESULTS_FILE).read_bytes())
    result = sweep("report", copy, "--heatmap", "targets.0.velocity_m_s")
    assert result.returncode == 0, result.stderr
    assert (copy / SUMMARY_FILE).read_text() == (out / SUMMARY_FILE).read_text()
    assert (copy / HEATMAP_FILE).stat().st_size > 0 and (copy / MARGINS_FILE).exists()
    bad = sweep("report", copy, "--heatmap", "gramian.eps")
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1


def test_the_same_sweep_twice_gives_identical_rows(
        local_sweep: tuple[Path, Path, subprocess.CompletedProcess], tmp_path: Path) -> None:
    path, out, _result = local_sweep
    again = sweep(path, "--out", tmp_path / "again", "--workers", "2")
    assert again.returncode == 0, again.stderr

    def comparable(rows: list[dict]) -> dict[str, dict]:
        return {r["key"]: {k: v for k, v in r.items() if k not in VARYING_KEYS} for r in rows}

    assert comparable(rows_of(tmp_path / "again")) == comparable(rows_of(out))
    rerun = sweep(path, "--out", out, "--workers", "2")  # everything done: nothing runs
    assert rerun.returncode == 0 and "8 done already" in rerun.stdout
    assert "Dask dashboard" not in rerun.stdout and len(rows_of(out)) == 8


def descendants(pid: int) -> list[psutil.Process]:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def wait_for_rows(out: Path, count: int, process: subprocess.Popen, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if (out / RESULTS_FILE).exists() and len(rows_of(out)) >= count:
            return
        assert process.poll() is None, "the sweep ended before it was to be stopped"
        time.sleep(0.05)
    raise AssertionError(f"fewer than {count} rows after {timeout_s} s")


def test_ctrl_c_stops_every_process_keeps_whole_rows_and_a_rerun_runs_the_rest(
        tmp_path: Path) -> None:
    path = write_sweep(tmp_path, seeds=(0, 9), duration_s=8.0)
    out = tmp_path / "out"
    process = subprocess.Popen([*SWEEP, str(path), "--out", str(out), "--workers", "2"],
                               cwd=ROOT, env=cli_env(**VERSION), stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        wait_for_rows(out, 2, process, 120.0)
        children = descendants(process.pid)
        assert len(children) >= 2  # the local cluster's worker processes
        os.killpg(process.pid, signal.SIGINT)  # a terminal's Ctrl-C: the whole group
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert process.returncode == 130, stdout + stderr
    assert "run the same command to run the rest" in stderr and "Traceback" not in stderr
    _gone, alive = psutil.wait_procs(children, timeout=10)
    assert not alive, f"left running: {alive}"
    first = rows_of(out)
    assert 2 <= len(first) < 10
    assert (out / RESULTS_FILE).read_text().endswith("\n")
    assert len({r["key"] for r in first}) == len(first)
    assert all(r["verdict"] == "OK" for r in first)  # no row for a stopped mission

    rerun = sweep(path, "--out", out, "--workers", "2")
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert f"{len(first)} done already" in rerun.stdout
    rows = rows_of(out)
    assert rows[:len(first)] == first  # kept as written
    assert sorted(r["seed"] for r in rows) == list(range(10))
    assert sorted(r["key"] for r in rows) == sorted(t.key for t in plan_sweep(path, out).tasks)


def test_a_worker_killed_mid_sweep_loses_no_point(tmp_path: Path) -> None:
    """A real ``dask scheduler`` and two ``dask worker`` processes over TCP on loopback; one
    worker gets SIGKILL once the first rows are in: its missions run on the other, and every
    point is in the file exactly once."""
    dask = console_script("dask", "dask")
    port = free_tcp_port()
    address = f"tcp://127.0.0.1:{port}"
    env = cli_env(**VERSION)
    started: list[subprocess.Popen] = []

    def start(*args: str) -> subprocess.Popen:
        process = subprocess.Popen([*dask, *args], cwd=ROOT, env=env,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                   start_new_session=True)
        started.append(process)
        return process

    try:
        start("scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard")
        workers = [start("worker", address, "--nthreads", "1", "--no-nanny",
                         "--no-dashboard", "--name", f"w{i}") for i in range(2)]
        path = write_sweep(tmp_path, seeds=(0, 11), duration_s=6.0)
        out = tmp_path / "out"
        process = subprocess.Popen([*SWEEP, str(path), "--out", str(out), "--scheduler",
                                    address], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, text=True, start_new_session=True)
        started.append(process)
        wait_for_rows(out, 2, process, 120.0)
        victim = workers[0]
        victim_pid = victim.pid
        victim.send_signal(signal.SIGKILL)
        victim.wait()
        stdout, stderr = process.communicate(timeout=180)
        assert process.returncode == 0, stdout + stderr
    finally:
        for p in started:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
    rows = rows_of(out)
    keys = [r["key"] for r in rows]
    assert len(keys) == len(set(keys)) == 12
    assert sorted(keys) == sorted(t.key for t in plan_sweep(path, out).tasks)
    assert all(r["verdict"] == "OK" for r in rows)
    after = rows[2:]
    assert any(not r["worker"].endswith(f":{victim_pid}") for r in after)
