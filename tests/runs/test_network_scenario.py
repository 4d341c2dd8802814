"""Case 2 with radios of 12 m (configs/case2_range.toml), in-process: without keeping links the
swarm splits and says so at once; keeping a spanning tree holds it together; the two new
invariants (kept_link, split_said) each fire when their condition is broken; the fixed graph
is unchanged bit for bit."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from swarm.core.network import NetworkParams
from swarm.observe.report import build_report, report_to_json
from swarm.runs.checks import check_invariants
from swarm.runs.network import network_summary
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config
from swarm.scenario.overrides import parse_assignment

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
RANGE = CONFIGS / "case2_range.toml"


def _run(*assignments: str):
    config = load_config(RANGE, overrides=[parse_assignment(a) for a in assignments])
    return run_reference(config, seed=0)


@pytest.fixture(scope="module")
def kept():
    return _run()


@pytest.fixture(scope="module")
def unkept():
    return _run("network.keep=none")


def test_keeping_the_tree_holds_the_swarm_together(kept) -> None:
    summary = network_summary(kept)
    assert summary is not None and summary.keep == "tree"
    assert summary.first_split_s is None and summary.max_components == 1
    assert summary.min_algebraic_connectivity > 0.5
    assert 0.0 < summary.min_kept_margin_m < 1.5  # the rows bound it: R − R_keep = 1 m
    assert summary.link_conflicts > 0  # the targets pulled, and the keep rows won
    assert not [v for v in check_invariants(kept)
                if v.invariant in ("kept_link", "split_said", "collision")]
    assert (kept.reached == 6).all()


def test_without_keeping_the_swarm_splits_and_says_so_at_once(unkept) -> None:
    config = unkept.config
    summary = network_summary(unkept)
    assert summary is not None and summary.first_split_s is not None
    assert 35.0 < summary.first_split_s < 48.0
    assert summary.split_parts == ((0, 1, 4, 5), (2, 3))
    window_s = (config.swarm.n_drones - 1 + config.network.reach_slack_steps) * 0.02
    assert 0.0 < summary.first_said_s - summary.first_split_s <= window_s + 0.02 + 1e-9
    assert sorted(set(unkept.reached[-1].tolist())) == [2, 4]
    violations = check_invariants(unkept)
    assert not [v for v in violations if v.invariant in ("kept_link", "split_said")]
    report = build_report(unkept)
    assert any("the swarm split at t = " in w and "said by a drone" in w
               for w in report.warnings)
    document = report_to_json(report)
    assert document["network"]["first_split_s"] == pytest.approx(summary.first_split_s)
    assert document["network"]["split_parts"] == [[0, 1, 4, 5], [2, 3]]


def test_a_kept_link_beyond_r_is_a_violation_naming_the_link(unkept) -> None:
    """The unkept run's positions judged as if it had kept the tree: the links that went
    beyond R are named, with when."""
    config = unkept.config
    as_kept = dataclasses.replace(config, network=dataclasses.replace(config.network,
                                                                      keep="tree"))
    record = dataclasses.replace(unkept, config=as_kept)
    (violation,) = [v for v in check_invariants(record) if v.invariant == "kept_link"]
    assert violation.limit == 12.0 and violation.worst_value > 12.0
    assert violation.subject.startswith("drones ") and "kept link" in violation.detail
    assert violation.first_time_s >= 30.0  # link 0–3 first, before the graph splits


def test_a_split_the_drones_do_not_count_is_a_violation(unkept) -> None:
    record = dataclasses.replace(unkept, reached=np.full_like(unkept.reached, 6))
    (violation,) = [v for v in check_invariants(record) if v.invariant == "split_said"]
    assert "counted 6 drones" in violation.detail and violation.first_time_s > 40.0
    early = unkept.reached.copy()
    early[:100, 3] = 5  # a split said where the radio had none
    (violation,) = [v for v in check_invariants(dataclasses.replace(unkept, reached=early))
                    if v.invariant == "split_said"]
    assert violation.subject == "drone 3" and violation.first_time_s < 2.0


def test_a_count_never_sent_says_nothing(unkept) -> None:
    """A realtime record keeps 0 where a drone's telemetry of a step never arrived (the
    launcher fills the velocities' gaps, not the counts): no split said, no violation, and
    the summary's first said split is where a count below N arrived."""
    reached = unkept.reached.copy()
    reached[-1, 4] = 0  # the last sample of drone 4 lost, as in CI's realtime run
    reached[:50, :] = 0  # and the first second of everyone's
    record = dataclasses.replace(unkept, reached=reached)
    assert not [v for v in check_invariants(record) if v.invariant == "split_said"]
    summary, before = network_summary(record), network_summary(unkept)
    assert summary is not None and before is not None
    assert summary.first_said_s == before.first_said_s is not None
    reached[60, 2] = 3  # a count below N that did arrive, where the radio had no split
    (violation,) = [v for v in check_invariants(dataclasses.replace(unkept, reached=reached))
                    if v.invariant == "split_said"]
    assert violation.subject == "drone 2" and "counted 3 drones" in violation.detail


def test_the_fixed_graph_is_unchanged_by_the_network_section() -> None:
    """case2 as shipped and with an explicit fixed [network] section: the same run bit for
    bit, with no radio in the record."""
    plain = load_config(CONFIGS / "case2.toml").with_duration(4.0)
    explicit = dataclasses.replace(plain, network=NetworkParams(topology="fixed"))
    a, b = run_reference(plain, seed=3), run_reference(explicit, seed=3)
    np.testing.assert_array_equal(a.drone_positions_m, b.drone_positions_m)
    np.testing.assert_array_equal(a.estimates, b.estimates)
    assert a.links is None and a.reached is None and network_summary(a) is None
