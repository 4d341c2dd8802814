"""Lossy and slow links in a realtime mission (issue 6, point 2): real processes, Zenoh,
MAVLink, with the fault injection of swarm.net.faults on every agent's consensus messages.

Case 1 with 10 % of the consensus messages lost, and separately with every one of them sent
2 steps late: every λ̄ copy stays ≥ ε − 0.01 once the barrier QP is on, and the final
position error of every drone's estimate is < 0.1 m.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.scenario.config import load_config

pytestmark = pytest.mark.wallclock

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
INJECTED = re.compile(r"injected consensus faults: (\d+) messages lost, (\d+) delayed (\d+) "
                      r"steps, of (\d+)")


@pytest.mark.slow
@pytest.mark.parametrize("fault", [["--drop-consensus", "0.1"], ["--delay-consensus", "2"]],
                         ids=["10%-lost", "2-steps-late"])
def test_case1_keeps_every_target_localized_over_a_faulty_link(fault: list[str],
                                                               tmp_path: Path) -> None:
    path = CONFIGS / "case1.toml"
    config = load_config(path)
    n = config.swarm.n_drones
    record = SwarmLauncher(LaunchOptions(
        config=config, config_path=str(path), seed=0, mode="realtime", log_dir=tmp_path,
        extra_agent_args=dict.fromkeys(range(n), fault)), log=lambda _line: None).run()

    # The faults were injected, at the rate asked for.
    lost = delayed = offered = 0
    for i in range(n):
        found = INJECTED.search((tmp_path / f"agent{i}.log").read_text())
        assert found, f"agent{i} did not report its injected faults"
        lost += int(found[1])
        delayed += int(found[2])
        offered += int(found[4])
    # One message per consensus round, K per step.
    assert offered > 0.9 * n * config.estimation.consensus_rounds * config.n_steps
    if fault[0] == "--drop-consensus":
        assert 0.085 < lost / offered < 0.115 and delayed == 0
    else:
        assert lost == 0 and delayed == offered

    # What the world saw of the vehicles (a failsafe hold explains a failure at once).
    failsafes = [line for line in (tmp_path / "world.log").read_text().splitlines()
                 if "failed safe" in line]
    active = record.times_s >= config.control.start_s
    lowest = float(record.lambda_bar[active].min())
    assert lowest >= config.gramian.epsilon - 0.01, (lowest, failsafes)
    final_error = float(record.position_errors()[-1].max())
    assert final_error < 0.1, (final_error, failsafes)
