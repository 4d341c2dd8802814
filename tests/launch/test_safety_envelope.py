"""The safety envelope in the process swarm (issue 18, point 4): configs/case2_envelope.toml
flown by real world and agent processes over Zenoh and MAVLink — in lockstep, bit for bit
the in-process run (conflict flags included), and in realtime, inside the envelope."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.runs.checks import check_invariants, min_envelope_margins
from swarm.scenario.config import load_config
from tests.helpers.reference_tools import assert_matches_reference

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs" / "case2_envelope.toml"


@pytest.mark.slow
def test_lockstep_flies_the_envelope_scenario_as_the_in_process_run() -> None:
    """All 50 s (the ceiling from t ≈ 24 s, the fence from t ≈ 46 s): the lockstep swarm's
    record equals the in-process one, and so do the steps it counted as conflicts."""
    config = load_config(CONFIG)
    launcher = SwarmLauncher(LaunchOptions(config=config, config_path=str(CONFIG), seed=0),
                             log=lambda _line: None)
    record = launcher.run()
    assert record.n_steps == config.n_steps
    reference = assert_matches_reference(config, record, seed=0)
    assert record.safety_conflict is not None
    assert np.array_equal(record.safety_conflict, reference.safety_conflict)
    assert check_invariants(record) == []
    counts = launcher.collector.counters()
    assert counts["safety_conflicts"] == int(reference.safety_conflict.sum()) > 0


@pytest.mark.wallclock
@pytest.mark.slow
def test_realtime_stays_inside_the_envelope() -> None:
    """30 s on the wall clock (the ceiling from t ≈ 24 s): every invariant holds, the
    envelope's included, and the drones reach the ceiling."""
    config = load_config(CONFIG).with_duration(30.0)
    launcher = SwarmLauncher(LaunchOptions(config=config, config_path=str(CONFIG), seed=0,
                                           mode="realtime"), log=lambda _line: None)
    record = launcher.run()
    assert check_invariants(record) == []
    margins = min_envelope_margins(record)
    assert margins["ceiling"] < 0.02, margins
