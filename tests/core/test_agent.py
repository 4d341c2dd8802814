"""The per-drone step: call order, bad input at its boundary, lost neighbours, QP fallbacks."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from swarm.config import load_config
from swarm.core.agent import AgentSetup, AgentStateError, ConsensusMessage, Detection, DroneAgent
from swarm.core.barrier import collision_row
from swarm.core.params import ControlParams, EstimationParams, GramianParams, PerceptionParams
from swarm.core.qp import QpSolver, build_local_qp
from swarm.reference import build_agent, run_reference

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def lone_agent(control: ControlParams, n_drones: int = 2, guess=(0.0, 0.0, 0.0)) -> DroneAgent:
    """Drone 0 of a two-drone swarm whose only neighbour is drone 1."""
    setup = AgentSetup(
        drone_id=0, n_drones=n_drones, n_targets=1, dt_s=0.02,
        neighbour_weights={1: 0.5}, perception=PerceptionParams(),
        estimation=EstimationParams(), gramian=GramianParams(), control=control)
    return DroneAgent(setup, np.array([guess]))


def run_alone(agent: DroneAgent, step: int, position, detections=(), beacons=None):
    agent.begin_step(step, np.asarray(position, float), list(detections))
    agent.consensus_round({})
    return agent.finish_step(beacons or {})


def test_calls_out_of_order_are_refused() -> None:
    agent = lone_agent(ControlParams())
    with pytest.raises(AgentStateError):
        agent.consensus_round({})
    with pytest.raises(AgentStateError):
        agent.finish_step({})
    agent.begin_step(0, np.array([0.0, 0.0, 3.0]), [])
    with pytest.raises(AgentStateError):
        agent.begin_step(1, np.array([0.0, 0.0, 3.0]), [])
    with pytest.raises(AgentStateError):
        agent.finish_step({})


def test_non_finite_position_is_a_clear_error() -> None:
    agent = lone_agent(ControlParams())
    with pytest.raises(ValueError, match="own position"):
        agent.begin_step(0, np.array([0.0, np.nan, 3.0]), [])


def test_bad_detections_are_counted_and_never_reach_the_filter() -> None:
    agent = lone_agent(ControlParams(start_s=0.0))
    bad = [Detection(0, np.array([np.nan, 0.0])), Detection(5, np.array([0.0, 0.0])),
           Detection(0, np.array([np.inf, 1.0])), Detection(0, np.array([0.1, 0.2, 0.3]))]
    result = run_alone(agent, 0, [0.0, 0.0, 3.0], bad)
    assert result.diagnostics.rejected_inputs == 4
    assert not result.diagnostics.detected.any()
    assert np.all(np.isfinite(result.velocity))
    assert np.all(np.isfinite(agent.target_estimates))


def test_missing_and_malformed_neighbour_messages_are_left_out_and_counted() -> None:
    agent = lone_agent(ControlParams())
    first = agent.begin_step(0, np.array([0.0, 0.0, 3.0]), [])
    poisoned = dataclasses.replace(first, sender=1, information=first.information * np.nan)
    agent.consensus_round({1: poisoned})
    result = agent.finish_step({})
    assert result.diagnostics.rejected_inputs == 1
    assert np.all(np.isfinite(agent.target_estimates))
    result = run_alone(agent, 1, [0.0, 0.0, 3.0])
    assert result.diagnostics.missing_neighbour_messages == 1
    assert agent.missing_neighbour_messages == 1 and agent.rejected_inputs == 1


def test_a_message_from_another_round_is_rejected() -> None:
    config = load_config(CONFIGS / "case1.toml")
    config = dataclasses.replace(
        config, estimation=dataclasses.replace(config.estimation, consensus_rounds=2))
    a, b = build_agent(config, 0, 0), build_agent(config, 0, 1)
    msg_a = a.begin_step(0, np.array([0.0, 0.0, 3.0]), [])
    msg_b = b.begin_step(0, np.array([1.0, 0.0, 3.0]), [])
    b.consensus_round({0: msg_a})
    # Round 1 of drone 0 fed with drone 1's *round-0* message again: wrong round.
    a.consensus_round({1: msg_b})
    assert a.consensus_round({1: msg_b}) is None
    assert a.rejected_inputs == 0  # counted at finish
    a.finish_step({})
    assert a.rejected_inputs == 1


def test_before_start_the_nominal_input_is_applied_without_qp() -> None:
    agent = lone_agent(ControlParams(start_s=1.0))
    result = run_alone(agent, 0, [0.0, 0.0, 3.0])
    assert result.diagnostics.qp_status == "inactive" and not result.diagnostics.control_active
    np.testing.assert_array_equal(result.velocity, np.zeros(3))


def test_hard_qp_infeasibility_falls_back_to_relaxed_and_is_counted() -> None:
    """A weight collapsed to ~0 (target estimate far outside the FoV) makes L_gψ1 ≈ 0 while
    the information is below ε: the hard QP (3.37) is infeasible (SPEC §9)."""
    agent = lone_agent(ControlParams(start_s=0.0, qp="hard"), guess=(40.0, 0.0, 0.0))
    for step in range(150):  # the Gramian copy decays below ε with no information coming in
        result = run_alone(agent, step, [0.0, 0.0, 3.0])
    assert result.diagnostics.lambda_bar[0] < 0.05
    assert agent.qp_fallbacks > 0
    assert result.diagnostics.qp_fallback
    assert np.all(np.abs(result.velocity) <= 3.0)


def test_collision_rows_keep_two_approaching_drones_apart() -> None:
    """Two drones whose nominal inputs fly them head-on, each solving its own QP with only its
    half of the collision constraint (SPEC §8): the pair never gets closer than Δ."""
    positions = [np.array([-1.0, 0.0, 3.0]), np.array([1.0, 0.0, 3.0])]
    nominal = [np.array([1.5, 0.0, 0.0]), np.array([-1.5, 0.0, 0.0])]
    solvers = [QpSolver(), QpSolver()]
    empty = np.zeros((0, 3))
    min_gap = np.inf
    for _ in range(300):
        velocities = []
        for i in (0, 1):
            row, lower = collision_row(positions[i], positions[1 - i], 0.5, 1.0)
            qp = build_local_qp(nominal[i], empty, np.zeros(0), empty, np.zeros(0),
                                row[None, :], np.array([lower]), np.zeros(0), relaxed=False,
                                slack_weight=1e6, weight_floor=1e-3, u_max=3.0)
            solution = solvers[i].solve(qp)
            assert solution.found
            velocities.append(solution.velocity)
        positions = [p + 0.02 * u for p, u in zip(positions, velocities, strict=True)]
        min_gap = min(min_gap, float(np.linalg.norm(positions[0] - positions[1])))
    assert 0.5 - 1e-6 <= min_gap < 0.6  # they do come close, and stop at Δ


def test_more_consensus_rounds_run_end_to_end() -> None:
    config = load_config(CONFIGS / "case1.toml").with_duration(1.5)
    config = dataclasses.replace(
        config, estimation=dataclasses.replace(config.estimation, consensus_rounds=3))
    record = run_reference(config, seed=0)
    assert np.all(np.isfinite(record.estimates))
    assert record.position_errors()[-1].max() < 0.1


def test_round0_message_carries_consensus_states() -> None:
    agent = lone_agent(ControlParams())
    msg = agent.begin_step(0, np.array([0.0, 0.0, 3.0]), [])
    assert isinstance(msg, ConsensusMessage) and msg.round == 0
    assert msg.gramian is not None and msg.gramian.shape == (1, 3, 3)
    np.testing.assert_allclose(msg.gramian[0], 2 * 0.05 * np.eye(3))
    assert msg.weight_mean is not None and 0 < msg.weight_mean[0] <= 1


def test_single_integrator_model_with_communicated_velocities() -> None:
    """The alternative target model (2.17-2.22): targets send their velocities; the filter
    state is the position only and still converges on Case 1's moving target."""
    config = load_config(CONFIGS / "case1.toml").with_duration(6.0)
    config = dataclasses.replace(
        config, estimation=dataclasses.replace(config.estimation, model="single_integrator"))
    record = run_reference(config, seed=0)
    assert record.estimates.shape[-1] == 3
    assert record.position_errors()[-1].max() < 0.05
