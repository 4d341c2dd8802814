"""Drone losses and summary columns in a sweep: the ``kill.at_s`` axis (each drone lost in
turn, one mission per drone), the per-cell ranges of row keys (``columns``), and a realtime
sweep on the real launcher whose rows say what the survivors held and said
(swarm.sweep.measures)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from swarm.sweep.plan import plan_sweep
from swarm.sweep.results import RESULTS_FILE, read_rows
from swarm.sweep.spec import SweepError, parse_spec
from swarm.sweep.stats import cell_stats, column_range
from swarm.sweep.summary import SUMMARY_FILE
from tests.helpers.cli_tools import ROOT, cli_env

THREE = ROOT / "tests" / "configs" / "case1_three.toml"
SWEEP = [sys.executable, "-m", "swarm.sweep.cli"]


@pytest.mark.parametrize(("data", "said"), [
    ({"axes": {"kill.at_s": [-1.0]}}, "mission times in seconds >= 0"),
    ({"axes": {"kill.at_s": ["soon"]}}, "mission times in seconds >= 0"),
    ({"kill_agents": ["1@2"], "axes": {"kill.at_s": [3.0]}}, "give one of the two"),
    ({"set": {"kill.at_s": 3.0}}, "kill.at_s is a grid axis"),
    ({"samples": {"count": 2, "ranges": {"kill.at_s": [1.0, 2.0]}}}, "not sampled"),
    ({"columns": ["tracking.velocity_error_rms_m_s"], "keep": ["margins"]}, "keep 'tracking'"),
    ({"columns": ["speed"]}, "'speed' is not a row key"),
    ({"columns": "loss.said"}, "columns: must be an array"),
])
def test_bad_loss_axes_and_columns_are_one_line(data: dict, said: str) -> None:
    with pytest.raises(SweepError) as caught:
        parse_spec({"base": "x.toml", **data})
    assert said in str(caught.value) and "\n" not in str(caught.value)


def write(directory: Path, body: str) -> Path:
    path = directory / "loss.toml"
    path.write_text(f'base = "{THREE}"\n{body}')
    return path


def test_each_drone_is_lost_in_turn_and_zero_is_the_baseline(tmp_path: Path) -> None:
    path = write(tmp_path, 'mode = "realtime"\nseeds = [0, 1]\n[axes]\n'
                           '"gramian.epsilon" = [0.05]\n"kill.at_s" = [0.0, 12.0]\n')
    tasks = plan_sweep(path, tmp_path / "out").tasks
    assert len(tasks) == 2 * (1 + 3)  # per seed: the baseline and each of the three drones
    lost = [(t.seed, t.params["kill.drone"], t.kill_agents) for t in tasks]
    assert lost[:5] == [(0, None, ()), (1, None, ()),  # cell by cell, then seed by seed
                        (0, 0, ((0, 12.0),)), (0, 1, ((1, 12.0),)), (0, 2, ((2, 12.0),))]
    assert all(t.axes == ("gramian.epsilon", "kill.at_s") for t in tasks)
    assert "kill" not in tasks[0].config_data  # not a config key
    assert len({t.key for t in tasks}) == len(tasks)


@pytest.mark.parametrize(("body", "said"), [
    ('seeds = [0, 0]\n[axes]\n"kill.at_s" = [12.0]\n', "--kill-agent needs --mode realtime"),
    ('mode = "realtime"\n[axes]\n"kill.at_s" = [30.0]\n',
     "kill.at_s = 30: not before the mission's end (30 s)"),
])
def test_a_loss_the_mission_cannot_have_is_refused(tmp_path: Path, body: str,
                                                  said: str) -> None:
    with pytest.raises(SweepError, match=said.replace("(", r"\(").replace(")", r"\)")):
        plan_sweep(write(tmp_path, body), tmp_path / "out")


def test_column_ranges_per_cell() -> None:
    rows = [{"key": "a", "seed": 0, "verdict": "OK", "axes": [], "params": {},
             "tracking": {"velocity_error_rms_m_s": 0.12},
             "loss": {"min_lambda_margin": [-0.02, 0.01], "said": True}},
            {"key": "b", "seed": 1, "verdict": "VIOLATED", "axes": [], "params": {},
             "tracking": {"velocity_error_rms_m_s": 0.03},
             "loss": {"min_lambda_margin": [0.004, -0.03], "said": None}},
            {"key": "c", "seed": 2, "verdict": "OK", "axes": [], "params": {},
             "tracking": {"velocity_error_rms_m_s": None},
             "loss": {"min_lambda_margin": [0.002, 0.0], "said": False}}]
    assert column_range(rows, "tracking.velocity_error_rms_m_s") == "0.03 … 0.12"
    assert column_range(rows, "loss.min_lambda_margin") == "-0.02 … 0.004; -0.03 … 0.01"
    assert column_range(rows, "loss.said") == "1 of 2"
    assert column_range(rows, "loss.final_error_m") == "—"
    assert column_range(rows[:1], "loss.said") == "1 of 1"
    (cell,) = cell_stats(rows, columns=["loss.said", "tracking.velocity_error_rms_m_s"])
    assert cell.columns == (("loss.said", "1 of 2"),
                            ("tracking.velocity_error_rms_m_s", "0.03 … 0.12"))


@pytest.mark.slow
@pytest.mark.wallclock
def test_a_realtime_loss_sweep_says_what_the_survivors_held(tmp_path: Path) -> None:
    """Three drones on the emulated vehicles, 8 s realtime missions, each agent killed in turn
    at 4 s, and one without a loss: four rows; the victims' rows say the loss from 4 s on
    (the survivors' figures), the baseline's has none; the tracking errors the agents measured
    are in every row (non-zero on SITL: tests/launch/test_sitl_missions.py); the summary shows
    the columns asked for."""
    path = write(tmp_path, 'mode = "realtime"\nseeds = [0, 0]\ntimeout_s = 120\n'
                           'columns = ["loss.min_lambda_margin", "loss.said", '
                           '"tracking.velocity_error_rms_m_s"]\n'
                           '[set]\n"scenario.duration_s" = 8.0\n[axes]\n'
                           '"kill.at_s" = [0.0, 4.0]\n')
    out = tmp_path / "out"
    result = subprocess.run([*SWEEP, str(path), "--out", str(out)], cwd=ROOT, env=cli_env(),
                            capture_output=True, text=True, timeout=400, check=False)
    rows = {r["params"]["kill.drone"]: r for r in read_rows(out / RESULTS_FILE)}
    assert sorted(rows, key=str) == [0, 1, 2, None], result.stdout + result.stderr
    assert "FAILED" not in {r["verdict"] for r in rows.values()}, result.stdout
    assert "loss" not in rows[None]
    for victim in (0, 1, 2):
        loss = rows[victim]["loss"]
        assert loss["victims"] == [victim]
        assert 4.0 <= loss["at_s"] <= 4.5  # the step after the victim's last telemetry
        assert len(loss["min_lambda_margin"]) == 1 and loss["final_error_m"] < 1.0
        assert loss["said"] in (None, True)  # a copy below the floor is always said
        assert rows[victim]["exit_code"] == 1  # launch-swarm names the loss
        assert "agent" in rows[victim]["reason"]
    for row in rows.values():
        tracking = row["tracking"]
        # measured every step; the emulated vehicles fly the command as given (ē = 0)
        assert 0.0 <= tracking["velocity_error_rms_m_s"] <= tracking["velocity_error_p95_m_s"]
        assert 0.0 <= tracking["position_error_rms_m"] <= tracking["position_error_p95_m"]
        assert row["rate_limit_releases"] >= 0 and row["reference_resets"] >= 0
    cells = json.loads((out / SUMMARY_FILE).read_text())
    assert [c["missions"] for c in cells] == [1, 3]
    assert set(cells[1]["columns"]) == {"loss.min_lambda_margin", "loss.said",
                                        "tracking.velocity_error_rms_m_s"}
    assert cells[0]["columns"]["loss.said"] == "—"
