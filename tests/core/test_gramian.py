"""Gramian copies with forgetting and consensus (SPEC §6, thesis 3.4, 3.29)."""

from __future__ import annotations

import numpy as np
from scipy.stats import special_ortho_group

from swarm.core.gramian import gramian_step, initial_gramian, true_gramian_step
from swarm.core.graph import CommunicationGraph
from swarm.core.params import GramianParams

PARAMS = GramianParams()
RHO = PARAMS.forgetting
DT = 0.02
INFO_GAIN = 1.0
N = 6
SCENARIO = CommunicationGraph(N, (*((i, (i + 1) % N) for i in range(N)), (0, 3), (1, 4)))


def _step(gramian, projector_mean, neighbours, consensus_gain=PARAMS.consensus_gain):
    return gramian_step(gramian, projector_mean, neighbours, n_agents=N, forgetting=RHO,
                        info_gain=INFO_GAIN, consensus_gain=consensus_gain, dt_s=DT)


def _random_projector_mean(rng: np.random.Generator) -> np.ndarray:
    """(1/N)Σ w_jΠ_j for N random bearings and weights."""
    total = np.zeros((3, 3))
    for _ in range(N):
        beta = rng.normal(size=3)
        beta /= np.linalg.norm(beta)
        total += rng.uniform(0.0, 1.0) * (np.eye(3) - np.outer(beta, beta))
    return total / N


def test_defaults_are_the_spec_values() -> None:
    """SPEC §6-§7, Table 4.1: ρ 0.6, ε 0.05, p −10, consensus gain 1."""
    assert (PARAMS.forgetting, PARAMS.epsilon) == (0.6, 0.05)
    assert (PARAMS.smooth_min_exponent, PARAMS.consensus_gain) == (-10.0, 1.0)


def test_initial_gramian_is_two_epsilon_identity() -> None:
    np.testing.assert_array_equal(initial_gramian(0.05), 0.1 * np.eye(3))


def test_identical_copies_with_exact_mean_follow_the_true_gramian() -> None:
    """All copies equal and s = (1/N)Σ wΠ exact: the consensus term vanishes and each copy
    takes exactly the centralized Euler step with information rate bΣ wΠ = bN s."""
    rng = np.random.default_rng(0)
    copy = truth = initial_gramian(PARAMS.epsilon)
    for _ in range(200):
        mean = _random_projector_mean(rng)
        copy = _step(copy, mean, [copy, copy, copy])
        truth = true_gramian_step(truth, INFO_GAIN * N * mean, forgetting=RHO, dt_s=DT)
        np.testing.assert_allclose(copy, truth, rtol=1e-13, atol=1e-15)


def test_copies_stay_exactly_symmetric() -> None:
    """Even from slightly asymmetric inputs, each step returns a symmetric matrix (SPEC §6)."""
    rng = np.random.default_rng(1)
    copy = initial_gramian(PARAMS.epsilon)
    for _ in range(50):
        mean = _random_projector_mean(rng) + 1e-9 * rng.normal(size=(3, 3))
        neighbour = copy + 1e-9 * rng.normal(size=(3, 3))
        copy = _step(copy, mean, [neighbour])
        np.testing.assert_array_equal(copy, copy.T)


def test_consensus_term_pulls_copies_together() -> None:
    """Different copies, same exact s, scenario graph: the largest disagreement between copies
    decreases every step and vanishes (< 1e-9 after 10 s), while the network average follows
    the centralized Gramian exactly (Σ_iΣ_j (G_j − G_i) = 0 on an undirected graph)."""
    rng = np.random.default_rng(2)
    copies = np.array([special_ortho_group.rvs(3, random_state=rng)
                       @ np.diag(rng.uniform(0.05, 2.0, 3))
                       @ special_ortho_group.rvs(3, random_state=rng).T for _ in range(N)])
    copies = 0.5 * (copies + np.swapaxes(copies, 1, 2))
    truth = copies.mean(axis=0)
    previous = np.inf
    for _ in range(500):
        mean = _random_projector_mean(rng)
        copies = np.array([_step(copies[i], mean, [copies[j] for j in SCENARIO.neighbours[i]])
                           for i in range(N)])
        truth = true_gramian_step(truth, INFO_GAIN * N * mean, forgetting=RHO, dt_s=DT)
        disagreement = max(np.abs(copies[i] - copies[j]).max() for i, j in SCENARIO.edges)
        assert disagreement < previous
        previous = disagreement
        np.testing.assert_allclose(copies.mean(axis=0), truth, rtol=1e-12, atol=1e-12)
    assert previous < 1e-9


def test_without_consensus_gain_copies_do_not_approach_each_other_faster_than_forgetting() -> None:
    """Control for the previous test: with the consensus gain → 0 the disagreement only decays
    by the forgetting factor (1 − ρΔT) per step."""
    rng = np.random.default_rng(3)
    a, b = initial_gramian(PARAMS.epsilon), np.diag([1.0, 2.0, 3.0])
    mean = _random_projector_mean(rng)
    a_next = _step(a, mean, [b], consensus_gain=1e-300)
    b_next = _step(b, mean, [a], consensus_gain=1e-300)
    np.testing.assert_allclose(a_next - b_next, (1.0 - RHO * DT) * (a - b), rtol=1e-13)


def test_works_on_a_stack_of_copies() -> None:
    """A (M, 3, 3) stack (one copy per target) steps like each copy separately."""
    rng = np.random.default_rng(4)
    stack = np.array([initial_gramian(PARAMS.epsilon), np.diag([0.5, 1.0, 1.5])])
    means = np.array([_random_projector_mean(rng) for _ in range(2)])
    neighbour = stack + 0.1
    stepped = _step(stack, means, [neighbour])
    for r in range(2):
        np.testing.assert_allclose(stepped[r], _step(stack[r], means[r], [neighbour[r]]),
                                   rtol=1e-15)


def test_constant_information_reaches_the_closed_form_steady_state() -> None:
    """For constant s, the Euler iterates are G_k = G* + (1 − ρΔT)^k (G_0 − G*) with
    G* = bN s/ρ: checked at k = 1000 (20 s) to 1e-12 of ‖G*‖, and the distance to G* has
    fallen by (1 − 0.012)^1000 ≈ 6e-6."""
    rng = np.random.default_rng(5)
    mean = _random_projector_mean(rng)
    steady = INFO_GAIN * N * mean / RHO
    start = initial_gramian(PARAMS.epsilon)
    copy = start
    for _ in range(1000):
        copy = _step(copy, mean, [copy, copy])
    expected = steady + (1.0 - RHO * DT) ** 1000 * (start - steady)
    scale = np.abs(steady).max()
    np.testing.assert_allclose(copy, expected, rtol=0, atol=1e-12 * scale)
    assert np.abs(copy - steady).max() < 1e-5 * np.abs(start - steady).max()
    # G* is a fixed point of the step.
    np.testing.assert_allclose(_step(steady, mean, [steady]), steady, rtol=1e-14, atol=1e-15)
