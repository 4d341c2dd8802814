"""Parity of the plain-float fast paths the agent's step runs with the readable forms the
finite-difference tests check (issue 15, point 1): ``perception_scalars`` ↔
``perception_terms``, ``smooth_min_scalars`` ↔ ``smooth_min_eigenvalue``,
``localization_barrier_scalars`` ↔ ``localization_barrier`` and ``bearing_formation_scalars``
↔ ``bearing_formation_velocity`` / ``bearing_error``, ``icf.StackedFilter`` ↔ ``posterior`` then
``predict`` per target, and the agent's packed consensus operator ↔ ``pi_consensus_step`` and
``gramian_step``, on random states in every regime: each
side of every perception threshold and right at it, eigenvalues far apart, nearly repeated
(gaps down to 1e-12 relative) and below the clipping floor.

Tolerance: both forms evaluate the same formulas in a different order (the fast barrier in the
eigenbasis of G, where Γ is never formed), so they agree to round-off: 1e-9 of each
quantity's scale (measured over these examples: 7e-15 for the barrier, 4e-16 for the
formation, bit for bit for the perception terms and λ̄); a factor of 1.0001 on one term of the
fast barrier fails it; so does a factor of 1.0001 on Q in the stacked filter or on one
coefficient of the consensus operator. The stacked filter's bound scales with the condition
number of V (its inverses are formed in another order).
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from swarm.core import icf
from swarm.core.agent import _consensus_operator
from swarm.core.barrier import localization_barrier, localization_barrier_scalars
from swarm.core.consensus_layout import ConsensusLayout
from swarm.core.dynamic_consensus import pi_consensus_step
from swarm.core.formation import (
    bearing_error,
    bearing_formation_scalars,
    bearing_formation_velocity,
)
from swarm.core.gramian import gramian_step
from swarm.core.params import ConsensusGains, GramianParams, PerceptionParams
from swarm.core.perception import perception_constants, perception_scalars, perception_terms
from swarm.core.smooth_min import EIGENVALUE_FLOOR, smooth_min_eigenvalue, smooth_min_scalars

from .finite_difference import drone_at

PARAMS = PerceptionParams()
CONSTANTS = perception_constants(PARAMS)
RTOL = 1e-9
EXAMPLES = settings(max_examples=300, deadline=None)

# Distances and off-axis cosines in every regime of w, at the thresholds and just beside them.
DISTANCES = st.one_of(
    st.floats(0.3, 9.0),
    st.sampled_from([PARAMS.d_min_th_m, PARAMS.d_max_th_m]),
    st.sampled_from([PARAMS.d_min_th_m, PARAMS.d_max_th_m]).flatmap(
        lambda d: st.floats(d - 1e-6, d + 1e-6)))
COSINES = st.one_of(
    st.floats(-0.9, 0.999),
    st.just(PARAMS.cos_alpha_th),
    st.floats(PARAMS.cos_alpha_th - 1e-7, PARAMS.cos_alpha_th + 1e-7))
ANGLES = st.floats(0.0, 2.0 * math.pi)
COORDS = st.floats(-5.0, 5.0)


def _close(fast, readable, scale: float | None = None) -> None:
    fast, readable = np.asarray(fast, dtype=float), np.asarray(readable, dtype=float)
    size = max(float(np.max(np.abs(readable))), 1e-300) if scale is None else scale
    np.testing.assert_allclose(fast, readable, rtol=0.0, atol=RTOL * size)


def _pair(target, distance, cosine, azimuth):
    target = np.array(target)
    return drone_at(target, distance, cosine, azimuth), target


@EXAMPLES
@given(st.tuples(COORDS, COORDS, COORDS), DISTANCES, COSINES, ANGLES)
# At the angular threshold the smooth step is flat: the readable gradient is exactly 0 and the
# fast one 2e-15 (found by a CI run).
@example(target=(0.0, 0.0, 0.0), distance=3.0, cosine=PARAMS.cos_alpha_th,
         azimuth=1.3455147415689412)
def test_perception_scalars_equal_perception_terms(target, distance, cosine, azimuth) -> None:
    drone, target = _pair(target, distance, cosine, azimuth)
    readable = perception_terms(drone, target, PARAMS)
    weight, grad, unit, dist, proj = perception_scalars(tuple(drone), tuple(target), CONSTANTS)
    _close(weight, readable.weight, 1.0)
    # ∂w/∂p is a sum of products of factors in [0, 1] and derivatives of order 1/d, so its
    # round-off scales with 1/d even where the gradient itself vanishes.
    grad_scale = max(float(np.max(np.abs(readable.weight_grad_drone))),
                     1.0 / readable.distance_m)
    _close(grad, readable.weight_grad_drone, grad_scale)
    _close(unit, readable.unit_bearing, 1.0)
    _close(dist, readable.distance_m)
    _close(np.reshape(proj, (3, 3)), readable.projector, 1.0)


def _gramian(eigenvalues, angles) -> np.ndarray:
    """V diag(λ) Vᵀ with V a rotation from three angles."""
    a, b, c = angles
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rx = np.array([[1, 0, 0], [0, math.cos(c), -math.sin(c)], [0, math.sin(c), math.cos(c)]])
    v = rz @ ry @ rx
    g = v @ np.diag(eigenvalues) @ v.T
    return 0.5 * (g + g.T)


# Eigenvalues: spread out, nearly repeated (relative gap down to 1e-12) or below the floor.
SPREAD = st.lists(st.floats(1e-3, 5.0), min_size=3, max_size=3)
NEAR_REPEATED = st.tuples(st.floats(1e-2, 3.0), st.sampled_from([1e-12, 1e-9, 1e-6, 1e-3]),
                          st.floats(1e-2, 3.0)).map(
    lambda t: [t[0], t[0] * (1.0 + t[1]), t[0] + t[2]])
CLIPPED = st.tuples(st.floats(-1e-6, EIGENVALUE_FLOOR), st.floats(1e-3, 2.0),
                    st.floats(1e-3, 2.0)).map(list)
EIGENVALUES = st.one_of(SPREAD, NEAR_REPEATED, CLIPPED)
ROTATIONS = st.tuples(ANGLES, ANGLES, ANGLES)
EXPONENTS = st.sampled_from([-10.0, -5.0, -2.0])


@EXAMPLES
@given(EIGENVALUES, ROTATIONS, EXPONENTS)
@example(eigenvalues=[4.0, 4.0, 0.75], angles=(0.0, 0.0, 0.0), p=-10.0)  # found by a run
def test_smooth_min_scalars_equal_smooth_min_eigenvalue(eigenvalues, angles, p) -> None:
    gramian = _gramian(eigenvalues, angles)
    readable = smooth_min_eigenvalue(gramian, p)
    raw, _ = np.linalg.eigh(gramian)  # what the agent (and the readable form) decomposes
    value, lam, g, hess, theta = smooth_min_scalars(tuple(float(x) for x in raw), p)
    _close(value, readable.value)
    _close(lam, readable.eigenvalues)
    _close(g, readable.eigen_gradient, 1.0)  # weights in [0, 1] summing to 1
    # Second derivatives are sums of terms of order f/λ_min² that may cancel (with p = −10
    # and λ = 4, 4, 0.75, h_00 is 1.6e-6 from terms near 1.3; the fast form's round-off was
    # 1.8e-15): judged against that natural size, not against what is left after the sum.
    natural = abs(float(readable.value)) / float(np.min(readable.eigenvalues)) ** 2  # floored
    h = readable.eigen_hessian
    _close(hess, [h[0, 0], h[1, 1], h[2, 2], h[0, 1], h[0, 2], h[1, 2]],
           max(float(np.abs(h).max()), natural))
    t = readable.divided_differences
    _close(theta, [t[0, 1], t[0, 2], t[1, 2]], max(float(np.abs(t).max()), natural))


@EXAMPLES
@given(EIGENVALUES, ROTATIONS, EXPONENTS, st.tuples(COORDS, COORDS, COORDS), DISTANCES,
       COSINES, ANGLES, st.lists(st.tuples(DISTANCES, COSINES, ANGLES), min_size=1,
                                 max_size=5),
       st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)), st.integers(1, 8),
       st.floats(0.1, 1.0), st.floats(0.01, 0.2), st.floats(0.1, 5.0))
def test_localization_barrier_scalars_equal_localization_barrier(
        eigenvalues, angles, p, target, distance, cosine, azimuth, others, velocity, n_agents,
        forgetting, epsilon, info_gain) -> None:
    gramian = _gramian(eigenvalues, angles)
    drone, target = _pair(target, distance, cosine, azimuth)
    terms = perception_terms(drone, target, PARAMS)
    # The consensus mean of wΠ̂ over a few drones, as the agent holds it.
    views = [perception_terms(drone_at(target, *o), target, PARAMS) for o in others]
    projector_mean = np.mean([v.weight * v.projector for v in [terms, *views]], axis=0)
    readable = localization_barrier(gramian, projector_mean, terms, np.array(velocity),
                                    n_agents=n_agents, forgetting=forgetting, epsilon=epsilon,
                                    exponent=p, info_gain=info_gain)
    raw, vectors = np.linalg.eigh(gramian)
    value, psi0, psi1, lie_g, lower = localization_barrier_scalars(
        tuple(float(x) for x in raw), vectors.tolist(), projector_mean.ravel().tolist(),
        perception_scalars(tuple(drone), tuple(target), CONSTANTS), velocity,
        n_agents=n_agents, forgetting=forgetting, epsilon=epsilon, exponent=p,
        info_gain=info_gain)
    _close(value, readable.lambda_bar)
    scale = max(abs(readable.psi1), abs(readable.psi0), readable.lambda_bar)
    _close(psi0, readable.psi0, scale)
    _close(psi1, readable.psi1, scale)
    # L_gi ψ1 = b[∇w ⟨Γ, Π̂⟩ + (2w/d̂)Π̂Γβ̂]: its size is that of b Σ g_k (‖∇w‖ + 2w/d̂), even
    # where the two parts cancel (a drone that does not see the target: ~1e-27).
    g_sum = float(np.sum(readable.smooth_min.eigen_gradient))
    lie_scale = info_gain * g_sum * (float(np.linalg.norm(terms.weight_grad_drone))
                                     + 2.0 * terms.weight / terms.distance_m)
    _close(lie_g, readable.lie_g, max(lie_scale, 1e-300))
    speed = float(np.linalg.norm(velocity))
    _close(lower, readable.lower_bound, max(abs(readable.lower_bound),
                                            abs(readable.coupling) / n_agents,
                                            lie_scale * speed, scale / n_agents))


@EXAMPLES
@given(st.tuples(COORDS, COORDS, COORDS),
       st.lists(st.tuples(st.tuples(COORDS, COORDS, COORDS), ANGLES, ANGLES), max_size=5),
       st.floats(0.1, 3.0))
def test_bearing_formation_scalars_equal_the_array_forms(own, neighbours, gain) -> None:
    own_p = np.array(own)
    positions, desired, listed = {}, {}, []
    for j, (offset, azimuth, elevation) in enumerate(neighbours):
        assume(float(np.linalg.norm(offset)) > 0.05)  # a neighbour is never on top of us
        position = own_p + np.array(offset)
        g_star = np.array([math.cos(elevation) * math.cos(azimuth),
                           math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])
        positions[j], desired[j] = position, g_star
        listed.append((tuple(position), tuple(g_star)))
    velocity, error = bearing_formation_scalars(own, listed, gain)
    _close(velocity, bearing_formation_velocity(own_p, positions, desired, gain), gain)
    _close(error, bearing_error(own_p, positions, desired), 1.0)


# -- the stacked ICF step and the packed consensus operator --------------------------------------


def _spd_stack(rng: np.random.Generator, m: int, n: int, condition: float) -> np.ndarray:
    """M symmetric positive-definite n×n matrices with eigenvalues spread over ``condition``."""
    stack = np.empty((m, n, n))
    for r in range(m):
        q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        eigenvalues = np.geomspace(1.0, condition, n) * rng.uniform(0.5, 20.0)
        stack[r] = (q * eigenvalues) @ q.T
        stack[r] = 0.5 * (stack[r] + stack[r].T)
    return stack


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(1, 3),
       model=st.sampled_from(["double_integrator", "single_integrator"]),
       n_agents=st.integers(2, 12), dt=st.floats(0.005, 0.1),
       noise=st.floats(1e-4, 1.0), condition=st.sampled_from([1.0, 10.0, 1e3, 1e5]))
def test_stacked_filter_equals_posterior_then_predict_per_target(
        seed, m, model, n_agents, dt, noise, condition) -> None:
    """``icf.StackedFilter`` (one LAPACK call for the stack, pinv(W⁺) from pinv(V)/N, the
    Kronecker product for A pinv(W⁺) Aᵀ) against ``posterior``, ``posterior_covariance``
    and ``predict`` (2.8-2.11, 2.21-2.22) target by target, with and without the
    communicated velocity."""
    rng = np.random.default_rng(seed)
    n = icf.state_dimension(model)
    information = _spd_stack(rng, m, n, condition)
    vector = rng.normal(size=(m, n)) * 10.0
    velocity = rng.normal(size=(m, 3)) if model == "single_integrator" else None
    transition = icf.transition_matrix(model, dt)
    fast = icf.StackedFilter(transition, noise, n_agents, dt)(information, vector, velocity)
    for r in range(m):
        state, info = icf.posterior(information[r], vector[r], n_agents)
        prior_state, prior_info = icf.predict(
            state, info, transition, noise,
            communicated_velocity=None if velocity is None else velocity[r], dt_s=dt)
        scale = condition * max(1.0, float(np.max(np.abs(state))))
        _close(fast[0][r], state, scale)
        _close(fast[1][r], prior_state, scale)
        _close(fast[2][r], prior_info, condition * float(np.max(np.abs(prior_info))))
        covariance = icf.posterior_covariance(info)
        _close(fast[3][r], covariance, condition * float(np.max(np.abs(covariance))))


def test_stacked_filter_takes_the_readable_path_for_a_singular_information() -> None:
    """One V not positive definite: every target goes through ``posterior``/``predict`` with
    the SVD pseudo-inverse, so the result is theirs exactly."""
    rng = np.random.default_rng(5)
    information = _spd_stack(rng, 2, 6, 10.0)
    information[1] = np.diag([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])  # velocity never seen
    vector = rng.normal(size=(2, 6))
    transition = icf.transition_matrix("double_integrator", 0.02)
    fast = icf.StackedFilter(transition, 0.01, 3, 0.02)(information, vector)
    for r in range(2):
        state, info = icf.posterior(information[r], vector[r], 3)
        prior_state, prior_info = icf.predict(state, info, transition, 0.01)
        assert np.array_equal(fast[0][r], state) and np.array_equal(fast[1][r], prior_state)
        assert np.array_equal(fast[2][r], prior_info)
        assert np.array_equal(fast[3][r], icf.posterior_covariance(info))


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(1, 3), n_neighbours=st.integers(0, 4),
       dt=st.floats(0.005, 0.1), rate_gain=st.floats(0.1, 20.0),
       forgetting=st.floats(0.05, 2.0), coupling=st.floats(0.1, 3.0))
def test_consensus_operator_equals_the_pi_consensus_and_gramian_steps(
        seed, m, n_neighbours, dt, rate_gain, forgetting, coupling) -> None:
    """The agent's packed consensus step (``_consensus_operator``: one gather, one product,
    one sum over z = [x, Σ_j (x − x_j), u, 0]) against ``pi_consensus_step`` (3.30) for wΠ̂
    and w with their own gains, and ``gramian_step`` (3.29) for the Gramian copies, whose
    source term is the consensus estimate s before the step."""
    rng = np.random.default_rng(seed)
    gram = GramianParams(forgetting=forgetting, consensus_gain=coupling,
                         projector_consensus=ConsensusGains(*rng.uniform(0.5, 10.0, 3)),
                         weight_consensus=ConsensusGains(*rng.uniform(0.5, 10.0, 3)))
    layout = ConsensusLayout(m)
    own = rng.normal(size=layout.size)
    others = [rng.normal(size=layout.size) for _ in range(n_neighbours)]
    local_input = rng.normal(size=10 * m)
    index, coefficients = _consensus_operator(layout, dt, gram, rate_gain)
    disagreement = sum((own - x for x in others), np.zeros(layout.size))
    z = np.concatenate((own, disagreement, local_input, [0.0]))
    fast = layout.unpack(np.add.reduce(z[index] * coefficients, axis=0))

    mine, theirs = layout.unpack(own), [layout.unpack(x) for x in others]
    new_s_p, new_eta_p = pi_consensus_step(
        mine["projector_mean"], mine["projector_integral"],
        local_input[:9 * m].reshape(m, 3, 3), [x["projector_mean"] for x in theirs],
        [x["projector_integral"] for x in theirs], gram.projector_consensus, dt)
    new_s_w, new_eta_w = pi_consensus_step(
        mine["weight_mean"], mine["weight_integral"], local_input[9 * m:],
        [x["weight_mean"] for x in theirs], [x["weight_integral"] for x in theirs],
        gram.weight_consensus, dt)
    new_g = gramian_step(mine["gramian"], mine["projector_mean"],
                         [x["gramian"] for x in theirs], n_agents=1, forgetting=forgetting,
                         info_gain=rate_gain, consensus_gain=coupling, dt_s=dt)
    scale = max(1.0, float(np.max(np.abs(z)))) * (1 + n_neighbours)
    for name, readable in (("projector_mean", new_s_p), ("weight_mean", new_s_w),
                           ("projector_integral", new_eta_p), ("weight_integral", new_eta_w),
                           ("gramian", new_g)):
        _close(fast[name], readable, scale)
