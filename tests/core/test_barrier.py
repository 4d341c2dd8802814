"""High Order CBF terms, weight-sum and collision rows (SPEC §8).

The central check is ``test_lie_derivatives_give_the_closed_loop_rate_of_psi1``: along the
true centralized flow (drones with velocities u_j, a moving target, Ġ = −ρG + bΣ_j w_jΠ_j),
dψ1/dt measured by finite differences in time must equal c + Σ_j (L_gj ψ1·u_j + d_j) built
from ``localization_barrier`` evaluated at each drone.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import special_ortho_group

from swarm.core.barrier import (
    collision_row,
    gramian_rate_model,
    localization_barrier,
    localization_share,
    robust_lower_bound,
    weight_sum_row,
)
from swarm.core.params import GramianParams, PerceptionParams
from swarm.core.perception import perception_terms, perception_weight
from swarm.core.smooth_min import inner, smooth_min_eigenvalue

from .finite_difference import (
    REGIMES,
    central_gradient,
    random_drone_in_regime,
    richardson_derivative,
    rk4,
)

PERCEPTION = PerceptionParams()
GRAMIAN = GramianParams()
RHO = GRAMIAN.forgetting
EPSILON = GRAMIAN.epsilon
INFO_GAIN = 1.0
EXPONENTS = [-4.0, -10.0, -30.0]


def _barrier(gramian, projector_mean, drone, target, target_velocity, n_agents, exponent):
    terms = perception_terms(drone, target, PERCEPTION)
    return localization_barrier(
        gramian, projector_mean, terms, target_velocity, n_agents=n_agents, forgetting=RHO,
        epsilon=EPSILON, exponent=exponent, info_gain=INFO_GAIN)


def _random_gramian(rng: np.random.Generator) -> np.ndarray:
    rotation = special_ortho_group.rvs(3, random_state=rng)
    return rotation @ np.diag(rng.uniform(0.05, 3.0, 3)) @ rotation.T


def _weighted_projector(drone: np.ndarray, target: np.ndarray) -> np.ndarray:
    terms = perception_terms(drone, target, PERCEPTION)
    return terms.weight * terms.projector


def _psi1(gramian: np.ndarray, projector_mean: np.ndarray, n_agents: int,
          exponent: float) -> float:
    """ψ1 = ⟨Γ(G), −ρG + bNs⟩ + λ̄(G) − ε, written from SPEC §8."""
    sm = smooth_min_eigenvalue(gramian, exponent)
    rate = -RHO * gramian + INFO_GAIN * n_agents * projector_mean
    return inner(sm.gradient, rate) + sm.value - EPSILON


def _six_drones(rng: np.random.Generator, target: np.ndarray) -> np.ndarray:
    """One drone in each regime of the weight (near/nominal/far × off-/on-axis)."""
    return np.array([random_drone_in_regime(rng, target, d, c) for d, c in REGIMES])


# Gradient checks in the drone position: F has the smoothness of w·Π (|F'''| ≲ 1e3 m⁻³ in the
# near regime, see test_perception), |F| ≤ 3, so with h = 1e-6 m truncation ≲ 2e-10 and
# round-off ≲ 3ε/h ≈ 7e-10: tolerance 1e-8.
FD_STEP_M = 1e-6
FD_ATOL = 1e-8


@pytest.mark.parametrize("exponent", EXPONENTS)
@pytest.mark.parametrize(("distance_regime", "cosine_regime"), REGIMES)
def test_lie_g_is_the_gradient_of_the_input_dependent_part(distance_regime: str,
                                                           cosine_regime: str,
                                                           exponent: float) -> None:
    """L_gi ψ1 = ∂F/∂p_i with F(p_i) = b⟨Γ(G), w(p_i, p̂)Π̂(p_i, p̂)⟩ at fixed G."""
    rng = np.random.default_rng(REGIMES.index((distance_regime, cosine_regime)) - int(exponent))
    for _ in range(4):
        target = rng.uniform(-1.0, 1.0, 3)
        drone = random_drone_in_regime(rng, target, distance_regime, cosine_regime)
        gramian = _random_gramian(rng)
        gamma = smooth_min_eigenvalue(gramian, exponent).gradient
        barrier = _barrier(gramian, _weighted_projector(drone, target), drone, target,
                           np.zeros(3), 6, exponent)

        def input_part(p: np.ndarray, g: np.ndarray = gamma, t: np.ndarray = target) -> float:
            return INFO_GAIN * inner(g, _weighted_projector(p, t))

        numeric = central_gradient(input_part, drone, FD_STEP_M)
        np.testing.assert_allclose(barrier.lie_g, numeric, rtol=0, atol=FD_ATOL)


@pytest.mark.parametrize(("distance_regime", "cosine_regime"), REGIMES)
def test_drift_is_the_rate_of_the_input_part_along_the_target_velocity(
    distance_regime: str, cosine_regime: str
) -> None:
    """d_i = ∂F/∂p̂·v̂: the central difference of F(p̂ + t v̂) in t at fixed p_i and G."""
    rng = np.random.default_rng(50 + REGIMES.index((distance_regime, cosine_regime)))
    for _ in range(5):
        target = rng.uniform(-1.0, 1.0, 3)
        drone = random_drone_in_regime(rng, target, distance_regime, cosine_regime)
        velocity = rng.uniform(-1.0, 1.0, 3)
        gramian = _random_gramian(rng)
        gamma = smooth_min_eigenvalue(gramian, -10.0).gradient
        barrier = _barrier(gramian, _weighted_projector(drone, target), drone, target,
                           velocity, 6, -10.0)

        def along_target(t: float, g=gamma, p=drone, r=target, v=velocity) -> float:
            return INFO_GAIN * inner(g, _weighted_projector(p, r + t * v))

        # |v̂| ≤ √3, so the step in p̂ is ≤ 1.7e-6 m: same error budget as the gradient test.
        numeric = (along_target(FD_STEP_M) - along_target(-FD_STEP_M)) / (2 * FD_STEP_M)
        assert barrier.drift == pytest.approx(numeric, rel=0, abs=2 * FD_ATOL)


@pytest.mark.parametrize("exponent", EXPONENTS)
def test_coupling_is_the_rate_of_psi1_along_the_model_gramian_rate(exponent: float) -> None:
    """With s fixed, Ġ(G) = −ρG + bNs and d/dt ψ1(G + tĠ)|₀ = D²λ̄[Ġ,Ġ] + (1 − ρ)⟨Γ,Ġ⟩ = c.

    Also checks ψ0, ψ1 and the row's lower bound −(c + ψ1)/N − d_i against SPEC §8. Richardson
    differences with a step moving G by 1e-4·λ_min have O(h⁴) truncation (< 1e-9 of the
    scale |D²λ̄[Ġ,Ġ]| + |⟨Γ,Ġ⟩| for p = −30); tolerance 1e-7 of that scale.
    """
    rng = np.random.default_rng(int(-exponent))
    n_agents = 6
    gramians = [_random_gramian(rng) for _ in range(4)]
    gramians += [2.0 * EPSILON * np.eye(3), np.diag([0.3, 0.3, 1.2])]  # start, repeated pair
    for gramian in gramians:
        target = rng.uniform(-1.0, 1.0, 3)
        drones = _six_drones(rng, target)
        mean = np.mean([_weighted_projector(p, target) for p in drones], axis=0)
        velocity = rng.uniform(-1.0, 1.0, 3)
        barrier = _barrier(gramian, mean, drones[0], target, velocity, n_agents, exponent)
        sm = smooth_min_eigenvalue(gramian, exponent)
        rate = gramian_rate_model(gramian, mean, n_agents, RHO, INFO_GAIN)
        np.testing.assert_allclose(rate, -RHO * gramian + INFO_GAIN * n_agents * mean)

        assert barrier.psi0 == pytest.approx(sm.value - EPSILON, rel=1e-14)
        assert barrier.psi1 == pytest.approx(_psi1(gramian, mean, n_agents, exponent),
                                             rel=1e-12, abs=1e-14)
        expected_lower = -(barrier.coupling + barrier.psi1) / n_agents - barrier.drift
        assert barrier.lower_bound == pytest.approx(expected_lower, rel=1e-14)

        step = 1e-4 * sm.eigenvalues[0] / np.linalg.norm(rate)
        numeric = richardson_derivative(
            lambda t, g=gramian, r=rate, s=mean: _psi1(g + t * r, s, n_agents, exponent), step)
        scale = abs(sm.second_derivative(rate)) + abs(inner(sm.gradient, rate))
        assert barrier.coupling == pytest.approx(numeric, rel=0, abs=1e-7 * scale)


def _information_rate(drones: np.ndarray, target: np.ndarray) -> np.ndarray:
    """bΣ_j w_jΠ_j of the true (centralized) Gramian, from true positions."""
    return INFO_GAIN * np.sum([_weighted_projector(p, target) for p in drones], axis=0)


def _psi1_along_flow(t: float, gramian, drones, velocities, target, target_velocity,
                     exponent) -> float:
    """ψ1 at time t of the closed loop: positions move linearly, G follows Ġ = −ρG + bΣwΠ.

    G(t) by RK4 with 8 steps of ≤ 1.25e-5 s: local error ~ (1.25e-5)⁵·|G⁽⁵⁾| per step, far
    below the round-off of G itself.
    """
    def rate(tau: float, g: np.ndarray) -> np.ndarray:
        return -RHO * g + _information_rate(drones + tau * velocities,
                                            target + tau * target_velocity)

    gramian_t = rk4(rate, gramian, t, 8) if t != 0.0 else gramian
    drones_t = drones + t * velocities
    target_t = target + t * target_velocity
    mean = _information_rate(drones_t, target_t) / (INFO_GAIN * len(drones))
    return _psi1(gramian_t, mean, len(drones), exponent)


@pytest.mark.parametrize("exponent", EXPONENTS)
@pytest.mark.parametrize("seed", range(8))
def test_lie_derivatives_give_the_closed_loop_rate_of_psi1(seed: int, exponent: float) -> None:
    """dψ1/dt along the centralized closed loop = c + Σ_j (L_gj ψ1·u_j + d_j) (SPEC §8).

    N = 7 drones (one in each weight regime plus one in a random regime: ψ1 is only C¹ across
    the weight thresholds, so no drone may cross one during the FD), velocities ≤ 3 m/s per
    axis, a moving target, G random SPD or the isotropic start 2εI; every term comes from
    ``localization_barrier`` with s = (1/N)Σ_j w_jΠ_j, v̂ = v_r and p̂ = p_r (exact estimates).
    Time derivative: Richardson-extrapolated central differences, O(h⁴). ψ1 varies on the time
    scale τ = λ_min/((1 − p)‖Ġ‖) (curvature |p|/λ of λ̄ times the speed of G: 1.3 ms at 2εI
    with p = −30), so h = min(1e-4 s, 0.05τ); positions then move ≤ 0.6 mm and every drone
    stays inside its regime. The mismatch shrinks 16× per halving of h (checked while writing
    this test) and is ≤ 1e-9 of the scale |c| + Σ|L_gj·u_j| + Σ|d_j|; the tolerance is 1e-7
    of it. A wrong sign or factor in any term is an O(1) error.
    """
    rng = np.random.default_rng(seed + 100 * int(-exponent))
    target = np.array([*rng.uniform(-1.0, 1.0, 2), 0.0])
    extra_regime = REGIMES[rng.integers(len(REGIMES))]
    drones = np.vstack([_six_drones(rng, target),
                        random_drone_in_regime(rng, target, *extra_regime)])
    n_agents = len(drones)
    velocities = rng.uniform(-3.0, 3.0, size=(n_agents, 3))
    target_velocity = np.array([*rng.uniform(-0.5, 0.5, 2), 0.0])
    gramian = 2.0 * EPSILON * np.eye(3) if seed % 4 == 0 else _random_gramian(rng)
    mean = _information_rate(drones, target) / (INFO_GAIN * n_agents)

    predicted = 0.0
    scale = 0.0
    coupling = None
    for drone, velocity in zip(drones, velocities, strict=True):
        barrier = _barrier(gramian, mean, drone, target, target_velocity, n_agents, exponent)
        if coupling is None:
            coupling = barrier.coupling
        assert barrier.coupling == coupling  # c depends only on (G, s), the same at every drone
        predicted += float(barrier.lie_g @ velocity) + barrier.drift
        scale += abs(float(barrier.lie_g @ velocity)) + abs(barrier.drift)
    predicted += coupling
    scale += abs(coupling)

    model_rate = -RHO * gramian + INFO_GAIN * n_agents * mean
    time_scale = np.linalg.eigvalsh(gramian)[0] / ((1.0 - exponent) * np.linalg.norm(model_rate))
    numeric = richardson_derivative(
        lambda t: _psi1_along_flow(t, gramian, drones, velocities, target, target_velocity,
                                   exponent),
        min(1e-4, 0.05 * time_scale))
    assert predicted == pytest.approx(numeric, rel=0, abs=1e-7 * scale)


def test_weight_sum_row_coefficients_and_bound() -> None:
    """Row = ∂w/∂p_i (FD) and bound = −(S_w − γ)/N − ∂w/∂p̂·v̂ with ∂w/∂p̂ by FD (SPEC §8)."""
    rng = np.random.default_rng(9)
    for distance_regime, cosine_regime in REGIMES:
        target = rng.uniform(-1.0, 1.0, 3)
        drone = random_drone_in_regime(rng, target, distance_regime, cosine_regime)
        velocity = rng.uniform(-1.0, 1.0, 3)
        weight_sum, gamma, n_agents = rng.uniform(0.0, 3.0), 0.5, 6
        terms = perception_terms(drone, target, PERCEPTION)
        coefficients, lower = weight_sum_row(terms, velocity, weight_sum, gamma, n_agents)
        wrt_drone = central_gradient(
            lambda p, t=target: perception_weight(p, t, PERCEPTION), drone, FD_STEP_M)
        wrt_target = central_gradient(
            lambda t, p=drone: perception_weight(p, t, PERCEPTION), target, FD_STEP_M)
        np.testing.assert_allclose(coefficients, wrt_drone, rtol=0, atol=FD_ATOL)
        expected = -(weight_sum - gamma) / n_agents - float(wrt_target @ velocity)
        assert lower == pytest.approx(expected, rel=0, abs=2 * FD_ATOL)


def _weight_sum(drones: np.ndarray, target: np.ndarray) -> float:
    return float(sum(perception_weight(p, target, PERCEPTION) for p in drones))


def _weight_sum_scene(rng: np.random.Generator, gamma: float):
    """Six drones (one per weight regime) around a moving target, their weight-sum rows
    (exact consensus: S_w = Σ_j w_j) and d/dt Σw for given drone velocities (central
    difference, h = 1e-6 s). Returns (weight sum, rows, rate of the weight sum)."""
    target = np.array([*rng.uniform(-1.0, 1.0, 2), 0.0])
    drones = _six_drones(rng, target)
    n_agents = len(drones)
    target_velocity = np.array([*rng.uniform(-0.5, 0.5, 2), 0.0])
    weight_sum = _weight_sum(drones, target)
    rows = [weight_sum_row(perception_terms(p, target, PERCEPTION), target_velocity,
                           weight_sum, gamma, n_agents) for p in drones]

    def rate_of_weight_sum(velocities: np.ndarray) -> float:
        step = 1e-6
        forward = _weight_sum(drones + step * velocities, target + step * target_velocity)
        backward = _weight_sum(drones - step * velocities, target - step * target_velocity)
        return (forward - backward) / (2.0 * step)

    return weight_sum, rows, rate_of_weight_sum


@pytest.mark.parametrize("seed", range(5))
def test_weight_sum_rows_together_enforce_the_centralized_cbf(seed: int) -> None:
    """Σ_j (a_j·u_j − lower_j) = d/dt Σ_j w_j + (S_w − γ) with S_w = Σ_j w_j (exact consensus).

    Hence if every drone satisfies its row (δw = 0), d/dt Σw ≥ −(Σw − γ), the CBF of
    h = Σ_j w_j − γ. The time derivative is a central difference with h = 1e-6 s (positions
    move ≤ 3 µm; error budget as in the gradient tests, times N = 6): tolerance 1e-7.
    """
    rng = np.random.default_rng(seed)
    gamma = 0.5
    weight_sum, rows, rate_of_weight_sum = _weight_sum_scene(rng, gamma)
    n_agents = len(rows)
    velocities = rng.uniform(-3.0, 3.0, size=(n_agents, 3))
    margins = sum(float(a @ u) - lower for (a, lower), u in zip(rows, velocities, strict=True))
    assert margins == pytest.approx(rate_of_weight_sum(velocities) + weight_sum - gamma,
                                    rel=0, abs=1e-7)

    # Project each velocity onto its row's half-space, then the centralized CBF must hold.
    for k, (a, lower) in enumerate(rows):
        gap = lower - float(a @ velocities[k])
        if gap > 0.0:
            assert a @ a > 0.0, "a drone with w = 1 has lower = −(S_w − γ)/N ≤ 0 here"
            velocities[k] += (gap + 1e-9) / float(a @ a) * a
    assert rate_of_weight_sum(velocities) >= -(weight_sum - gamma) - 1e-7


@pytest.mark.parametrize("seed", range(20))
def test_collision_rows_of_a_pair_enforce_the_centralized_cbf(seed: int) -> None:
    """Both halves satisfied ⇒ ḣ_ij ≥ −α h_ij with h_ij = ‖p_i − p_j‖² − Δ² (SPEC §8).

    Exactly: (a_i·u_i − l_i) + (a_j·u_j − l_j) = ḣ_ij + α h_ij, with ḣ_ij = 2(p_i − p_j)ᵀ(u_i − u_j)
    from the definition; this holds to round-off (terms ≤ 1e2, so 1e-10 absolute).
    """
    rng = np.random.default_rng(seed)
    distance, gain = 0.5, 1.0
    p_i = rng.uniform(-2.0, 2.0, 3)
    offset = rng.normal(size=3)
    p_j = p_i + offset * rng.uniform(0.6, 3.0) / np.linalg.norm(offset)  # Δ < ‖p_i − p_j‖ ≤ R_ca
    h = float((p_i - p_j) @ (p_i - p_j)) - distance**2
    row_i, lower_i = collision_row(p_i, p_j, distance, gain)
    row_j, lower_j = collision_row(p_j, p_i, distance, gain)
    np.testing.assert_allclose(row_i, 2.0 * (p_i - p_j))
    assert lower_i == pytest.approx(-0.5 * gain * h, rel=1e-14)
    assert lower_j == lower_i

    u_i, u_j = rng.uniform(-3.0, 3.0, 3), rng.uniform(-3.0, 3.0, 3)
    h_rate = 2.0 * float((p_i - p_j) @ (u_i - u_j))
    margins = float(row_i @ u_i) - lower_i + float(row_j @ u_j) - lower_j
    assert margins == pytest.approx(h_rate + gain * h, rel=0, abs=1e-10)

    for row, lower, u in ((row_i, lower_i, u_i), (row_j, lower_j, u_j)):
        gap = lower - float(row @ u)
        if gap > 0.0:
            u += gap / float(row @ row) * row
    h_rate = 2.0 * float((p_i - p_j) @ (u_i - u_j))
    assert h_rate >= -gain * h - 1e-10


def _onto_tightened_boundary(row: np.ndarray, lower: float, bound: float) -> np.ndarray:
    """A velocity on the boundary of a·u ≥ b + ē‖a‖ (``robust_lower_bound``), random along it."""
    return (robust_lower_bound(lower, tuple(row.tolist()), bound) / float(row @ row)) * row


def _worst_error(row: np.ndarray, bound: float) -> np.ndarray:
    return -bound * row / np.linalg.norm(row)


@pytest.mark.parametrize("seed", range(6))
def test_tightened_localization_rows_hold_the_hocbf_on_the_flown_velocity(seed: int) -> None:
    """The robust margin on 3.32 (SPEC §8 rows tightened by ē‖L_gi ψ1‖), through the whole
    closed loop: drones whose row matters (‖L_gi ψ1‖ > 0.01) on the boundary of their
    tightened row, flying u_j + e_j with the worst tracking error e_j = −ē a_j/‖a_j‖, meet their
    share exactly, so dψ1/dt = −ψ1 + (what the other drones contribute); any error within ē
    gives more; without the margin the worst error takes Σ_j ē‖a_j‖ off. The others (weights
    ≈ 0, whose rows only slacks could meet) fly random commands with random errors, the same
    in every case. Time derivatives as in
    ``test_lie_derivatives_give_the_closed_loop_rate_of_psi1`` (same tolerance).
    """
    rng = np.random.default_rng(500 + seed)
    exponent, bound = -10.0, 0.3
    target = np.array([*rng.uniform(-1.0, 1.0, 2), 0.0])
    drones = _six_drones(rng, target)
    n_agents = len(drones)
    target_velocity = np.array([*rng.uniform(-0.5, 0.5, 2), 0.0])
    gramian = _random_gramian(rng)
    mean = _information_rate(drones, target) / (INFO_GAIN * n_agents)
    barriers = [_barrier(gramian, mean, p, target, target_velocity, n_agents, exponent)
                for p in drones]
    psi1 = barriers[0].psi1
    matters = [float(np.linalg.norm(b.lie_g)) > 0.01 for b in barriers]
    assert any(matters)

    def within_bound(count: int) -> np.ndarray:
        errors = rng.normal(size=(count, 3))
        return errors * bound * rng.uniform(0.0, 1.0, (count, 1)) / np.linalg.norm(
            errors, axis=1, keepdims=True)

    others = rng.uniform(-1.0, 1.0, (n_agents, 3)) + within_bound(n_agents)
    offset = sum(float(b.lie_g @ v) - b.lower_bound
                 for b, v, m in zip(barriers, others, matters, strict=True) if not m)
    random_errors = within_bound(n_agents)

    def flown(command, error) -> np.ndarray:
        return np.array([command(b) + error(k, b) if m else others[k]
                         for k, (b, m) in enumerate(zip(barriers, matters, strict=True))])

    def tightened(b) -> np.ndarray:
        return _onto_tightened_boundary(b.lie_g, b.lower_bound, bound)

    def untightened(b) -> np.ndarray:
        return (b.lower_bound / float(b.lie_g @ b.lie_g)) * b.lie_g

    def worst(_k: int, b) -> np.ndarray:
        return _worst_error(b.lie_g, bound)

    shortfall = bound * sum(float(np.linalg.norm(b.lie_g))
                            for b, m in zip(barriers, matters, strict=True) if m)
    model_rate = -RHO * gramian + INFO_GAIN * n_agents * mean
    time_scale = np.linalg.eigvalsh(gramian)[0] / ((1.0 - exponent) * np.linalg.norm(model_rate))
    step = min(1e-4, 0.05 * time_scale)

    def rate_of_psi1(velocities: np.ndarray) -> float:
        return richardson_derivative(
            lambda t: _psi1_along_flow(t, gramian, drones, velocities, target, target_velocity,
                                       exponent), step)

    on_boundary = flown(tightened, worst)
    scale = abs(barriers[0].coupling) + sum(abs(b.drift) + abs(float(b.lie_g @ v))
                                            for b, v in zip(barriers, on_boundary, strict=True))
    tolerance = 1e-7 * scale
    assert rate_of_psi1(on_boundary) == pytest.approx(-psi1 + offset, rel=0, abs=tolerance)
    assert rate_of_psi1(flown(tightened, lambda k, b: random_errors[k])) \
        >= -psi1 + offset - tolerance
    assert rate_of_psi1(flown(untightened, worst)) == pytest.approx(
        -psi1 + offset - shortfall, rel=0, abs=tolerance)
    assert shortfall > 100 * tolerance  # the margin is not lost in the tolerance


@pytest.mark.parametrize("seed", range(10))
def test_tightened_collision_and_weight_rows_hold_on_the_flown_velocity(seed: int) -> None:
    """Collision halves and weight-sum rows tightened by ē‖a‖: with the worst tracking error
    the centralized CBFs (ḣ_ij ≥ −α h_ij; d/dt Σw ≥ −(Σw − γ)) hold with equality; with any
    error within ē they hold; without the margin the worst error breaks them."""
    rng = np.random.default_rng(700 + seed)
    bound, distance, gain = 0.4, 0.5, 1.0
    p_i = rng.uniform(-2.0, 2.0, 3)
    offset = rng.normal(size=3)
    p_j = p_i + offset * rng.uniform(0.6, 3.0) / np.linalg.norm(offset)
    h = float((p_i - p_j) @ (p_i - p_j)) - distance**2
    flown = []
    for own, other in ((p_i, p_j), (p_j, p_i)):
        row, lower = collision_row(own, other, distance, gain)
        flown.append(_onto_tightened_boundary(row, lower, bound) + _worst_error(row, bound))
    assert 2.0 * float((p_i - p_j) @ (flown[0] - flown[1])) == pytest.approx(-gain * h,
                                                                             abs=1e-10)
    row, lower = collision_row(p_i, p_j, distance, gain)
    assert robust_lower_bound(lower, tuple(row.tolist()), bound) == pytest.approx(
        lower + bound * 2.0 * np.linalg.norm(p_i - p_j), rel=1e-14)

    gamma = 0.5
    weight_sum, rows, rate_of_weight_sum = _weight_sum_scene(rng, gamma)
    active = [(a, lower) for a, lower in rows if float(a @ a) > 1e-4]
    assert active
    tight = np.array([_onto_tightened_boundary(a, lower, bound) + _worst_error(a, bound)
                      if float(a @ a) > 1e-4 else np.zeros(3) for a, lower in rows])
    loose = np.array([(lower / float(a @ a)) * a + _worst_error(a, bound)
                      if float(a @ a) > 1e-4 else np.zeros(3) for a, lower in rows])
    inactive = sum(lower for a, lower in rows if float(a @ a) <= 1e-4)

    # Σ_j (a_j·ṗ_j − lower_j) = d/dt Σw + (S_w − γ) (the test above); on the tightened
    # boundary with the worst error every active a_j·ṗ_j = lower_j.
    assert rate_of_weight_sum(tight) == pytest.approx(-(weight_sum - gamma) - inactive,
                                                      abs=1e-7)
    shortfall = bound * sum(float(np.linalg.norm(a)) for a, _ in active)
    assert rate_of_weight_sum(loose) == pytest.approx(
        -(weight_sum - gamma) - inactive - shortfall, abs=1e-7)


def test_a_drone_that_does_not_see_the_target_has_no_weighted_share_whatever_the_estimate(
        ) -> None:
    """k_ir = 0 when w_ir = 0 (or NaN), also when the estimate S_wr is 0 or negative (a
    consensus estimate is not bound to stay positive): no division by zero. A positive weight
    takes its part w/S_w, and all of it (1) when the estimate is not above its own weight."""
    for estimate in (1.0, 0.0, -0.5):
        assert localization_share("weighted", 0.0, estimate, 3) == 0.0
        assert localization_share("weighted", float("nan"), estimate, 3) == 0.0
    assert localization_share("weighted", 0.4, 1.6, 3) == 0.25
    for estimate in (0.4, 0.2, 0.0, -1.0):
        assert localization_share("weighted", 0.4, estimate, 3) == 1.0
