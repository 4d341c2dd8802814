"""Case 2, seed 5, in process, with each share of the localization condition
(``[control] localization_share``, thesis 3.27-3.28).

With the equal shares of SPEC §8 (k = 1/N) a λ̄ copy of target 1 falls below ε − tol: drones
that do not see the target hold a share they can only meet with a slack. With the weighted
shares (k_ir = w_ir / max(S_wr, w_ir)) the same mission holds every invariant of its config.
docs/method.md, "Each drone's share of the localization condition", has the sweep over seeds
0-99.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from swarm.runs.checks import check_invariants
from swarm.runs.reference import run_reference
from swarm.scenario.config import ScenarioConfig, load_config

CASE2 = Path(__file__).resolve().parents[2] / "configs" / "case2.toml"
SEED = 5

pytestmark = pytest.mark.slow


def _with_share(config: ScenarioConfig, share: str) -> ScenarioConfig:
    return dataclasses.replace(
        config, control=dataclasses.replace(config.control, localization_share=share))


def test_case2_seed5_breaks_lambda_bar_with_equal_shares_and_holds_with_weighted() -> None:
    config = load_config(CASE2)
    assert config.control.localization_share == "equal"  # the shipped default (SPEC §8)
    equal = check_invariants(run_reference(config, seed=SEED))
    assert [v.invariant for v in equal] == ["lambda_bar"], [str(v) for v in equal]
    assert equal[0].subject.startswith("target 1"), str(equal[0])

    weighted = run_reference(_with_share(config, "weighted"), seed=SEED)
    assert check_invariants(weighted) == []
