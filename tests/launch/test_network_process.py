"""Radios with a range in the process swarm (issue 44, point 6): the world's radio decides
whose messages each agent takes; in lockstep the record equals the in-process run bit for bit
(links, reach counts and keep-row conflicts included); in realtime a split is said by the
agents, the world's links recorded, the report warns."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.observe.report import build_report
from swarm.runs.checks import check_invariants
from swarm.runs.network import network_summary
from swarm.scenario.config import load_config, write_resolved_config
from swarm.scenario.overrides import parse_assignment
from tests.helpers.reference_tools import assert_matches_reference

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs" / "case2_range.toml"


def _config(tmp_path: Path, *assignments: str, duration_s: float = 36.0):
    """The range scenario with ``--set``s, and the resolved file its processes read (as
    launch-swarm writes it when given --set)."""
    config = load_config(CONFIG, overrides=[parse_assignment(a) for a in assignments]
                         ).with_duration(duration_s)
    return config, str(write_resolved_config(config, tmp_path / "config.json"))


@pytest.mark.slow
@pytest.mark.parametrize("keep", ["tree", "none"])
def test_lockstep_flies_the_range_scenario_as_the_in_process_run(keep: str,
                                                                tmp_path: Path) -> None:
    """R = 8 m, 36 s: without keeping, the swarm splits at ~33 s; with the tree it holds.
    Either way the lockstep swarm's record equals the in-process one, with the same links,
    the same reach counts and the same conflicts."""
    config, path = _config(tmp_path, "network.range_m=8", f"network.keep={keep}")
    launcher = SwarmLauncher(LaunchOptions(config=config, config_path=path, seed=0),
                             log=lambda _line: None)
    record = launcher.run()
    assert record.n_steps == config.n_steps
    reference = assert_matches_reference(config, record, seed=0)
    for name in ("links", "reached", "link_conflict"):
        ours, theirs = getattr(record, name), getattr(reference, name)
        assert ours is not None and np.array_equal(ours, theirs), name
    summary = network_summary(record)
    assert summary is not None
    if keep == "none":
        assert summary.first_split_s is not None and summary.first_said_s is not None
    else:
        assert summary.first_split_s is None and int(record.link_conflict.sum()) > 0
        assert launcher.collector.counters()["link_conflicts"] == int(
            reference.link_conflict.sum())
    assert not [v for v in check_invariants(record)
                if v.invariant in ("kept_link", "split_said", "collision")]


@pytest.mark.wallclock
@pytest.mark.slow
def test_realtime_agents_say_the_split_and_the_report_names_it(tmp_path: Path) -> None:
    """R = 5 m without keeping, 36 s on the wall clock (in-process the swarm splits at
    28.7 s; in realtime on a busy machine it came at 30.6 s): the world's links split the
    swarm, each agent logs that its part is smaller, and the report's warning names it."""
    config, path = _config(tmp_path, "network.range_m=5", "network.keep=none",
                           duration_s=36.0)
    logs = tmp_path / "logs"
    launcher = SwarmLauncher(LaunchOptions(config=config, config_path=path, seed=0,
                                           mode="realtime", log_dir=logs),
                             log=lambda _line: None)
    record = launcher.run()
    summary = network_summary(record)
    assert summary is not None and summary.first_split_s is not None
    assert summary.first_said_s is not None
    assert summary.first_said_s - summary.first_split_s < 1.0
    said = [i for i in range(config.swarm.n_drones)
            if "the swarm has split" in (logs / f"agent{i}.log").read_text()]
    assert said == list(range(config.swarm.n_drones)), said
    report = build_report(record, "realtime")
    assert any("the swarm split at t = " in w for w in report.warnings)
    assert not [v for v in check_invariants(record)
                if v.invariant in ("split_said", "collision")]
