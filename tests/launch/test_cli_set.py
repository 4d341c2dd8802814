"""``launch-swarm --set KEY=VALUE`` (swarm.scenario.overrides): the same validation as the
file, one line and exit 2 for a bad value, and the world and agents run the config as set."""

from __future__ import annotations

from tests.helpers.cli_tools import launch_swarm_in_process, run_cli

CASE1 = "configs/case1.toml"


def test_set_changes_the_in_process_run() -> None:
    result = launch_swarm_in_process(CASE1, "--inprocess", "--headless", "--set",
                                     "scenario.duration_s=2", "--set", "gramian.epsilon=0.06")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "100 steps" in result.stdout and "ε = 0.06" in result.stdout


def test_a_bad_set_is_one_line_and_exit_2() -> None:
    bad_value = launch_swarm_in_process(CASE1, "--inprocess", "--set", "gramian.epsilon=-1")
    assert bad_value.returncode == 2
    assert bad_value.stderr.strip().splitlines() == [
        "launch-swarm: config error: configs/case1.toml: gramian.epsilon must be a finite "
        "number > 0 (got -1.0)"]
    malformed = launch_swarm_in_process(CASE1, "--inprocess", "--set", "epsilon")
    assert malformed.returncode == 2 and len(malformed.stderr.strip().splitlines()) == 1
    unknown = launch_swarm_in_process(CASE1, "--inprocess", "--set", "gramian.eps=1")
    assert unknown.returncode == 2 and "gramian.eps: unknown key" in unknown.stderr


def test_the_process_swarm_flies_the_config_as_set() -> None:
    """Three drones instead of the file's six: had the world or an agent read the file, the
    swarm would not match and the lockstep mission would not complete."""
    result = run_cli(CASE1, "--headless", "--set", "swarm.n_drones=3", "--set",
                     "scenario.duration_s=1.5")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "verdict: OK" in result.stdout
    assert "world + 3 agents (lockstep)" in result.stdout
