"""``launch-swarm``: exit codes 0/1/2, one-line errors, no tracebacks, determinism.

The command runs as a subprocess (``python -m swarm.launch.cli``, and once the console script) in
the environment of a non-interactive run: stdout/stderr are pipes and COLUMNS is unset.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from swarm.runs.checks import summarize_drones, summarize_targets
from swarm.runs.record import RunRecord
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config
from tests.helpers.cli_tools import launch_swarm_in_process, run_cli

ROOT = Path(__file__).resolve().parents[2]
CASE1 = "configs/case1.toml"


def nonempty_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip()]


def assert_usage_error(result: subprocess.CompletedProcess[str]) -> None:
    """Exit 2, something on stderr, nothing on stdout, no traceback."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    assert "Traceback" not in result.stdout + result.stderr
    assert result.stdout == ""
    assert nonempty_lines(result.stderr)


# -- a short successful run ----------------------------------------------------------------


@pytest.fixture(scope="module")
def short_run() -> subprocess.CompletedProcess[str]:
    return run_cli(CASE1, "--inprocess", "--headless", "--duration", "2")


def test_short_case1_run_exits_0_with_verdict_ok(
        short_run: subprocess.CompletedProcess[str]) -> None:
    assert short_run.returncode == 0, short_run.stderr
    assert "verdict: OK" in short_run.stdout
    assert "Traceback" not in short_run.stdout + short_run.stderr
    assert "seed 0" in short_run.stdout
    assert "100 steps" in short_run.stdout  # 2 s / 0.02 s
    assert short_run.stderr.strip() == ""


def test_headless_run_logs_progress_lines(short_run: subprocess.CompletedProcess[str]) -> None:
    logs = [line for line in short_run.stdout.splitlines() if line.startswith("t=")]
    assert logs, short_run.stdout
    assert "λ̄ min" in logs[0]


def test_console_script_next_to_the_interpreter() -> None:
    script = Path(sys.executable).with_name("launch-swarm")
    if not script.exists():
        pytest.skip(f"no console script at {script}")
    result = run_cli(CASE1, "--inprocess", "--headless", "--duration", "1.1", "--seed", "7",
                     command=[str(script)])
    assert result.returncode == 0, result.stderr
    assert "seed 7" in result.stdout
    assert "verdict: OK" in result.stdout


# -- bad command lines ---------------------------------------------------------------------

BAD_ARGUMENTS = {
    "duration_negative": ["--duration", "-1"],
    "duration_zero": ["--duration", "0"],
    "duration_nan": ["--duration", "nan"],
    "duration_inf": ["--duration", "inf"],
    "duration_text": ["--duration", "abc"],
    "seed_negative": ["--seed", "-1"],
    "seed_float": ["--seed", "1.5"],
    "seed_text": ["--seed", "abc"],
    "seed_too_large": ["--seed", str(2**63)],
    "unknown_option": ["--bogus"],
    "gcs_port_zero": ["--gcs", "127.0.0.1:0"],
    "gcs_no_port": ["--gcs", "localhost:"],
    "gcs_unknown_host": ["--gcs", "no-such-host.invalid:14550"],
}


@pytest.fixture(scope="module")
def bad_argument_results() -> dict[str, subprocess.CompletedProcess[str]]:
    """Each bad command line through ``launch-swarm``'s ``main`` in this process (a process
    each cost 7 s of suite; ``test_bad_arguments_fail_the_same_way_as_processes`` shows a
    process answers the same)."""
    return {name: launch_swarm_in_process(CASE1, "--inprocess", "--headless", *args)
            for name, args in BAD_ARGUMENTS.items()}


def test_bad_arguments_fail_the_same_way_as_processes(
        bad_argument_results: dict[str, subprocess.CompletedProcess[str]]) -> None:
    """As processes, for a value error, a type error and an unknown option: the same exit
    code, the same line, nothing else (the process boundary adds nothing)."""
    sample = ("duration_negative", "seed_text", "unknown_option")
    with ThreadPoolExecutor(max_workers=len(sample)) as pool:
        results = dict(zip(sample, pool.map(
            lambda name: run_cli(CASE1, "--inprocess", "--headless", *BAD_ARGUMENTS[name]),
            sample), strict=True))
    for name, result in results.items():
        here = bad_argument_results[name]
        assert (result.returncode, result.stdout, result.stderr) == (
            here.returncode, here.stdout, here.stderr), name


@pytest.mark.parametrize("name", BAD_ARGUMENTS)
def test_bad_argument_exits_2_without_traceback(
        name: str, bad_argument_results: dict[str, subprocess.CompletedProcess[str]]) -> None:
    result = bad_argument_results[name]
    assert_usage_error(result)
    last = nonempty_lines(result.stderr)[-1]
    assert last.startswith("launch-swarm: error: ")
    if name != "unknown_option":
        assert BAD_ARGUMENTS[name][0] in last  # names the option
        assert repr(BAD_ARGUMENTS[name][1]) in last  # and echoes the value


@pytest.mark.parametrize("name", BAD_ARGUMENTS)
def test_bad_argument_error_is_one_line(
        name: str, bad_argument_results: dict[str, subprocess.CompletedProcess[str]]) -> None:
    assert len(nonempty_lines(bad_argument_results[name].stderr)) == 1


@pytest.mark.parametrize(("args", "said"), [
    (["--gcs-control"], "--gcs-control needs --gcs HOST:PORT"),
    (["--gcs", "14550", "--inprocess"], "with --inprocess there are none"),
])
def test_ground_station_options_that_cannot_be_served_exit_2_with_one_line(
        args: list[str], said: str) -> None:
    result = launch_swarm_in_process(CASE1, "--headless", *args)
    assert_usage_error(result)
    assert nonempty_lines(result.stderr) == [nonempty_lines(result.stderr)[0]]
    assert said in result.stderr


def test_missing_config_file_exits_2_with_one_line() -> None:
    result = run_cli("configs/nope.toml", "--inprocess")
    assert_usage_error(result)
    assert nonempty_lines(result.stderr) == [
        "launch-swarm: config error: configs/nope.toml: no such file"]


def test_without_inprocess_the_process_swarm_runs() -> None:
    """Issue 3 replaced the old "not available yet" error: the default is the process swarm."""
    result = run_cli(CASE1, "--headless", "--duration", "1.5")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "mission running" in result.stdout
    assert "verdict: OK" in result.stdout


def test_duration_before_control_start_is_a_config_error() -> None:
    result = run_cli(CASE1, "--inprocess", "--duration", "0.5")
    assert_usage_error(result)
    assert "control.start_s" in " ".join(result.stderr.split())


def test_duration_shorter_than_one_step_exits_2() -> None:
    result = run_cli(CASE1, "--inprocess", "--duration", "0.01")
    assert_usage_error(result)
    assert len(nonempty_lines(result.stderr)) == 1


def test_config_whose_drones_cannot_be_placed_exits_2(tmp_path: Path) -> None:
    text = (ROOT / CASE1).read_text()
    text = text.replace("n_drones = 6", "n_drones = 2")
    text = text.replace(
        "edges = [[0, 1], [1, 2], [2, 3], [3, 4], [4, 5], [5, 0], [0, 3], [1, 4]]",
        "edges = [[0, 1]]")
    text = text.replace("initial_box_size_m = [4.0, 4.0, 2.0]",
                        "initial_box_size_m = [1.0, 0.0, 0.0]")
    path = tmp_path / "segment.toml"
    path.write_text(text)
    result = run_cli(str(path), "--inprocess", "--headless", "--duration", "1.1")
    assert_usage_error(result)


# -- determinism ---------------------------------------------------------------------------

TIMING_FIELDS = {"step_us", "wall_time_s", "world_clock_rate"}  # wall-clock measurements


def _short_record(seed: int | None) -> RunRecord:
    return run_reference(load_config(ROOT / CASE1).with_duration(1.2), seed)


@pytest.fixture(scope="module")
def seed0_twice() -> tuple[RunRecord, RunRecord]:
    return _short_record(None), _short_record(0)


def test_same_seed_gives_bit_identical_runs(seed0_twice: tuple[RunRecord, RunRecord]) -> None:
    """1.2 s of Case 1 (past control.start_s = 1 s, so the QP runs) twice: identical arrays."""
    first, second = seed0_twice
    assert first.seed == second.seed == 0
    assert first.n_steps == 60
    compared = 0
    for field in dataclasses.fields(RunRecord):
        if field.name in TIMING_FIELDS | {"config", "seed"}:
            continue
        a, b = getattr(first, field.name), getattr(second, field.name)
        if field.name in {"links", "reached", "link_conflict"}:  # the radio's: a range only
            assert a is None and b is None, field.name
            continue
        assert isinstance(a, np.ndarray), field.name
        assert np.array_equal(a, b, equal_nan=True), field.name
        compared += 1
    assert compared >= 15
    # The summaries printed by the CLI agree too (timings masked).
    assert summarize_targets(first) == summarize_targets(second)
    mask = {"mean_step_us": 0.0, "p99_step_us": 0.0}
    assert ([dataclasses.replace(d, **mask) for d in summarize_drones(first)]
            == [dataclasses.replace(d, **mask) for d in summarize_drones(second)])


def test_a_different_seed_gives_a_different_run(
        seed0_twice: tuple[RunRecord, RunRecord]) -> None:
    other = _short_record(1)
    assert other.seed == 1
    assert not np.array_equal(other.drone_positions_m[0], seed0_twice[0].drone_positions_m[0])
    assert not np.array_equal(other.estimates, seed0_twice[0].estimates)
    # The targets are the same truth whatever the seed.
    np.testing.assert_array_equal(other.target_positions_m, seed0_twice[0].target_positions_m)
