"""Cases 1-3 at full length (seed 0, in process) with the design's QP solver, PIQP
(``[control] qp_solver = "piqp"``): every agent's QP goes to PIQP, none falls back, and the
runs hold the SPEC invariants of their configs, as with DAQP (tests/runs/test_scenarios.py).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from swarm.core.drone_step import StepDiagnostics
from swarm.runs.checks import check_invariants
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs"

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("case", ["case1", "case2", "case3"])
def test_the_cases_fly_with_piqp_and_hold_their_invariants(case: str) -> None:
    config = load_config(CONFIGS / f"{case}.toml")
    assert config.control.qp_solver == "daqp"  # the shipped default
    config = dataclasses.replace(config, control=dataclasses.replace(config.control,
                                                                     qp_solver="piqp"))
    statuses: set[str] = set()

    def on_step(_step: int, diagnostics: list[StepDiagnostics]) -> None:
        statuses.update(d.qp_status for d in diagnostics)

    record = run_reference(config, seed=0, on_step=on_step)
    assert "PIQP_SOLVED" in statuses, statuses
    assert not any(status.startswith("DAQP") for status in statuses), statuses
    assert not record.qp_fallback.any()
    assert check_invariants(record) == []
