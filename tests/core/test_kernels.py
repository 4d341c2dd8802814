"""The compiled kernels the agent's step runs (``swarm.core.kernels``) against the readable
forms the finite-difference tests check, and their own derivatives by central differences
(issue 16: the compiled form is parity-tested against its formula):

- ``perception`` ↔ ``perception_terms`` (SPEC §3), in every regime, at each threshold and
  right beside it;
- ``symmetric_eigen`` ↔ LAPACK's ``np.linalg.eigh``; ``smooth_min`` ↔ ``smooth_min_eigenvalue``
  (SPEC §7) for eigenvalues far apart, nearly repeated (relative gaps down to 1e-12) and
  below the clipping floor;
- ``perception_barrier`` ↔ ``perception_terms`` then ``localization_barrier`` (SPEC §8), one
  target and a stack;
- ``qp_rows`` ↔ the localization rows of ``localization_barrier`` with each
  ``localization_share``, then the rows of ``weight_sum_row``, ``collision_row`` and
  ``robust_lower_bound`` (SPEC §8), and the envelope's;
- ``icf.StackedFilter`` (``filter_stack``) ↔ ``posterior``, ``posterior_covariance`` and
  ``predict`` per target (SPEC §5, 2.8-2.11, 2.21-2.22), and its pseudo-inverse fallback;
- bad buffers are refused with a one-line error.

Tolerance: the forms evaluate the same formulas in a different order (the barrier in the
eigenbasis of G, where Γ is never formed; Jacobi rotations against LAPACK's tridiagonal
method; inverses from a Cholesky factor against LU), so they agree to round-off: 1e-9 of each
quantity's scale. Measured over these examples: bit for bit for the perception terms,
~1e-14 for the barrier. The filter's bound scales with the condition number of V.
"""

from __future__ import annotations

import math
from typing import get_args

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.stats import special_ortho_group

from swarm.core import icf, kernels
from swarm.core.barrier import (
    LocalizationBarrier,
    collision_row,
    localization_barrier,
    localization_share,
    robust_lower_bound,
    weight_sum_row,
)
from swarm.core.consensus_message import PAIR_NAMES, message_layout
from swarm.core.params import LocalizationShare, PerceptionParams
from swarm.core.perception import PerceptionTerms, perception_terms
from swarm.core.smooth_min import (
    EIGENVALUE_FLOOR,
    NEAR_REPEATED_LOG_GAP,
    smooth_min_eigenvalue,
)
from swarm.errors import VigilError

from .finite_difference import REGIMES, central_gradient, drone_at, random_drone_in_regime

PARAMS = PerceptionParams()
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


def _close(fast, readable, scale: float | None = None) -> None:
    fast, readable = np.asarray(fast, dtype=float), np.asarray(readable, dtype=float)
    size = max(float(np.max(np.abs(readable))), 1e-300) if scale is None else scale
    np.testing.assert_allclose(fast, readable, rtol=0.0, atol=RTOL * size)


def _pair(target, distance, cosine, azimuth):
    target = np.array(target)
    return drone_at(target, distance, cosine, azimuth), target


def _gramian(eigenvalues, angles) -> np.ndarray:
    """V diag(λ) Vᵀ with V a rotation from three angles."""
    a, b, c = angles
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rx = np.array([[1, 0, 0], [0, math.cos(c), -math.sin(c)], [0, math.sin(c), math.cos(c)]])
    v = rz @ ry @ rx
    g = v @ np.diag(eigenvalues) @ v.T
    return 0.5 * (g + g.T)


# -- perception (SPEC §3) ----------------------------------------------------------------------


@EXAMPLES
@given(st.tuples(COORDS, COORDS, COORDS), DISTANCES, COSINES, ANGLES)
# At the angular threshold the smooth step is flat: the readable gradient is exactly 0 and the
# fast one 2e-15 (found by a CI run).
@example(target=(0.0, 0.0, 0.0), distance=3.0, cosine=PARAMS.cos_alpha_th,
         azimuth=1.3455147415689412)
def test_perception_equals_perception_terms(target, distance, cosine, azimuth) -> None:
    drone, target = _pair(target, distance, cosine, azimuth)
    readable = perception_terms(drone, target, PARAMS)
    weight, grad, unit, dist, proj = kernels.perception(drone, target, PARAMS)
    _close(weight, readable.weight, 1.0)
    # ∂w/∂p is a sum of products of factors in [0, 1] and derivatives of order 1/d, so its
    # round-off scales with 1/d even where the gradient itself vanishes.
    grad_scale = max(float(np.max(np.abs(readable.weight_grad_drone))),
                     1.0 / readable.distance_m)
    _close(grad, readable.weight_grad_drone, grad_scale)
    _close(unit, readable.unit_bearing, 1.0)
    _close(dist, readable.distance_m)
    _close(np.reshape(proj, (3, 3)), readable.projector, 1.0)


# -- eigen-decomposition and smooth minimum (SPEC §7) ---------------------------------------------


@EXAMPLES
@given(EIGENVALUES, ROTATIONS)
def test_symmetric_eigen_is_an_eigendecomposition_as_lapack_gives(eigenvalues, angles) -> None:
    """Eigenvalues ascending as LAPACK's to round-off of the largest, eigenvectors orthonormal
    and reproducing G; where eigenvalues are apart, each eigenvector LAPACK's up to sign."""
    gramian = _gramian(eigenvalues, angles)
    values, vectors = kernels.symmetric_eigen(gramian)
    lapack_values, lapack_vectors = np.linalg.eigh(gramian)
    scale = max(float(np.max(np.abs(lapack_values))), 1e-300)
    _close(values, lapack_values, scale)
    assert np.all(np.diff(values) >= 0.0)
    _close(vectors.T @ vectors, np.eye(3), 1.0)
    _close(vectors @ np.diag(values) @ vectors.T, gramian, scale)
    for k in range(3):
        gap = min(abs(lapack_values[k] - lapack_values[j]) for j in range(3) if j != k)
        if gap > 1e-3 * scale:  # a well-defined direction: round-off / gap of it
            sign = math.copysign(1.0, float(vectors[:, k] @ lapack_vectors[:, k]))
            _close(sign * vectors[:, k], lapack_vectors[:, k], 1e3 * scale / gap)


def test_symmetric_eigen_refuses_a_non_finite_matrix() -> None:
    for bad in (math.nan, math.inf):
        gramian = np.eye(3)
        gramian[0, 1] = gramian[1, 0] = bad
        with pytest.raises(np.linalg.LinAlgError):
            kernels.symmetric_eigen(gramian)


@EXAMPLES
@given(EIGENVALUES, ROTATIONS, EXPONENTS)
@example(eigenvalues=[4.0, 4.0, 0.75], angles=(0.0, 0.0, 0.0), p=-10.0)  # found by a run
def test_smooth_min_equals_smooth_min_eigenvalue(eigenvalues, angles, p) -> None:
    gramian = _gramian(eigenvalues, angles)
    readable = smooth_min_eigenvalue(gramian, p)
    # The readable form's own eigenvalues (the eigensolvers agree to round-off of the largest
    # eigenvalue, not of the smallest: test_symmetric_eigen_...).
    raw, _ = np.linalg.eigh(gramian)
    value, lam, g, hess, theta = kernels.smooth_min(raw, p)
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


# -- the localization barrier (SPEC §8) ---------------------------------------------------------


def _constants(n_agents, forgetting, epsilon, p, info_gain) -> np.ndarray:
    return kernels.barrier_constants(PARAMS, n_agents=n_agents, forgetting=forgetting,
                                     epsilon=epsilon, exponent=p, info_gain=info_gain)


@EXAMPLES
@given(EIGENVALUES, ROTATIONS, EXPONENTS, st.tuples(COORDS, COORDS, COORDS), DISTANCES,
       COSINES, ANGLES, st.lists(st.tuples(DISTANCES, COSINES, ANGLES), min_size=1,
                                 max_size=5),
       st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)), st.integers(1, 8),
       st.floats(0.1, 1.0), st.floats(0.01, 0.2), st.floats(0.1, 5.0))
# An eigenvalue at the clipping floor beside a repeated pair (found by a run: the eigensolvers
# put it on either side of the floor).
@example(eigenvalues=[1e-9, 1.0, 1.0], angles=(0.0, 1.0, 0.0), p=-10.0, target=(0.0, 0.0, 0.0),
         distance=1.0, cosine=PARAMS.cos_alpha_th, azimuth=0.0, others=[(3.0, 0.9, 0.5)],
         velocity=(0.9, -0.2, 0.0), n_agents=4, forgetting=0.5, epsilon=0.04, info_gain=3.0)
# An eigenvalue at the floor beside two others (found by a run, see the tolerance below).
@example(eigenvalues=[1e-9, 1.0, 0.03125], angles=(1.0, 0.0, 1.0), p=-2.0,
         target=(0.0, 0.0, 0.0), distance=1.0, cosine=PARAMS.cos_alpha_th, azimuth=0.0,
         others=[(9.0, PARAMS.cos_alpha_th, 0.834098221951543)], velocity=(0.0, 0.0, 0.0),
         n_agents=1, forgetting=1.0, epsilon=0.125, info_gain=1.0)
def test_perception_barrier_equals_localization_barrier(
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
    # The estimate as the agent holds it: [p̂; v̂] (the velocity part is not read here).
    estimate = np.concatenate((target, [9.0, 9.0, 9.0]))
    fast_terms, (value, psi0, psi1, lie_g, lower) = kernels.barrier(
        drone, estimate, np.array(velocity), gramian, projector_mean,
        _constants(n_agents, forgetting, epsilon, p, info_gain))
    assert fast_terms == kernels.perception(drone, target, PARAMS)
    # Two backward-stable eigensolvers (Jacobi here, LAPACK in the readable form) agree on
    # each eigenvalue to a few ulps of the largest, not of the smallest: with λ = 1e-9, 1, 1
    # they differ by 5e-17 (found by a run; Jacobi's is the closer one).
    eigen_round_off = 16.0 * np.finfo(float).eps * max(abs(x) for x in eigenvalues)
    _close(value, readable.lambda_bar, max(readable.lambda_bar, eigen_round_off / RTOL))

    # An eigenvalue at the clipping floor (EIGENVALUE_FLOOR) is a kink of the readable form:
    # a perturbation of Γ within that round-off (±eigen_round_off along an eigenvector) moves
    # the derivatives across it by more than RTOL of their size (found by a run: λ = 1e-9,
    # 1, 1/32, p = -2; the two eigensolvers landed 1.6e-16 apart and the lower bound moved by
    # 9.8e-8 of 0.28, exactly what the readable form does under that perturbation). Each
    # output agrees to within its spread under those perturbations, or RTOL of its size.
    def at(perturbed):
        return localization_barrier(perturbed, projector_mean, terms, np.array(velocity),
                                    n_agents=n_agents, forgetting=forgetting, epsilon=epsilon,
                                    exponent=p, info_gain=info_gain)

    _, eigenvectors = np.linalg.eigh(gramian)
    nearby = [at(gramian + sign * eigen_round_off * np.outer(v, v))
              for v in eigenvectors.T for sign in (1.0, -1.0)]

    def spread(get) -> float:  # as a scale for _close: the largest move, over RTOL
        return max(float(np.max(np.abs(np.asarray(get(r)) - np.asarray(get(readable)))))
                   for r in nearby) / RTOL

    scale = max(abs(readable.psi1), abs(readable.psi0), readable.lambda_bar,
                eigen_round_off / RTOL)
    _close(psi0, readable.psi0, max(scale, spread(lambda r: r.psi0)))
    _close(psi1, readable.psi1, max(scale, spread(lambda r: r.psi1)))
    # L_gi ψ1 = b[∇w ⟨Γ, Π̂⟩ + (2w/d̂)Π̂Γβ̂]: its size is that of b Σ g_k (‖∇w‖ + 2w/d̂), even
    # where the two parts cancel (a drone that does not see the target: ~1e-27).
    g_sum = float(np.sum(readable.smooth_min.eigen_gradient))
    lie_scale = info_gain * g_sum * (float(np.linalg.norm(terms.weight_grad_drone))
                                     + 2.0 * terms.weight / terms.distance_m)
    _close(lie_g, readable.lie_g, max(lie_scale, 1e-300, spread(lambda r: r.lie_g)))
    speed = float(np.linalg.norm(velocity))
    _close(lower, readable.lower_bound, max(abs(readable.lower_bound),
                                            abs(readable.coupling) / n_agents,
                                            lie_scale * speed, scale / n_agents,
                                            spread(lambda r: r.lower_bound)))


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(1, 4), n=st.sampled_from([3, 6]))
def test_perception_barrier_of_a_stack_is_each_target_alone(seed, m, n) -> None:
    """The agent's call for M targets = M one-target calls, bit for bit (no state between
    targets, each row from its own inputs)."""
    rng = np.random.default_rng(seed)
    drone = rng.normal(size=3) + np.array([0.0, 0.0, 3.0])
    estimates = rng.normal(size=(m, n))
    velocities = rng.normal(size=(m, 3))
    gramians = np.array([_gramian(rng.uniform(0.01, 3.0, 3), rng.uniform(0, 6, 3))
                         for _ in range(m)])
    means = np.array([_gramian(rng.uniform(0.0, 1.0, 3), rng.uniform(0, 6, 3))
                      for _ in range(m)])
    constants = _constants(4, 0.5, 0.05, -10.0, 1.3)
    terms, barriers = kernels.perception_barrier(drone, estimates, velocities,
                                                 gramians.reshape(-1), means.reshape(-1),
                                                 constants)
    for r in range(m):
        alone = kernels.barrier(drone, estimates[r], velocities[r], gramians[r], means[r],
                                constants)
        assert (terms[r], barriers[r]) == alone


def test_perception_barrier_refuses_a_non_finite_gramian() -> None:
    gramians = np.tile(np.eye(3).reshape(-1), 2)
    gramians[13] = math.nan  # target 1
    with pytest.raises(np.linalg.LinAlgError, match="non-finite"):
        kernels.perception_barrier(np.zeros(3), np.ones((2, 6)), np.zeros((2, 3)), gramians,
                                   np.zeros(18), _constants(4, 0.5, 0.05, -10.0, 1.3))


# -- the QP's rows --------------------------------------------------------------------------


def _row_constants(n_agents: float, *, gamma: float = 0.3, radius_m: float = 1.5,
                   gain: float = 1.0, bound: float = 0.0, rule: str = "equal") -> dict[str, float]:
    """``qp_rows``' constants by name (collision distance 0.5 m)."""
    return {"n_agents": n_agents, "gamma": gamma, "collision_radius_m": radius_m,
            "collision_distance_m": 0.5, "collision_gain": gain,
            "tracking_error_bound_m_s": bound,
            "localization_share": kernels.LOCALIZATION_SHARES[rule]}


def _readable_rows(terms, velocities, weight_sums, position, others, envelope_rows,
                   envelope_lower, constants: dict[str, float],
                   barriers: list[LocalizationBarrier]):
    """The rows of SPEC §8 from the readable functions, one by one: (rows (R × 3), lower).
    The localization rows' bounds are ``barriers``' with each drone's share of (3.27)."""
    n, gamma, radius, delta, gain, bound = (
        constants[name] for name in ("n_agents", "gamma", "collision_radius_m",
                                     "collision_distance_m", "collision_gain",
                                     "tracking_error_bound_m_s"))
    rule = {code: name for name, code in kernels.LOCALIZATION_SHARES.items()}[
        constants["localization_share"]]
    rows = [row[kernels.ROW.LIE_G] for row in terms]
    lower = [b.shared_lower_bound(localization_share(rule, row[kernels.ROW.WEIGHT], s_w, int(n)))
             for b, row, s_w in zip(barriers, terms, weight_sums, strict=True)]
    for row, velocity, s_w in zip(terms, velocities, weight_sums, strict=True):
        pair = PerceptionTerms(row[kernels.ROW.WEIGHT], row[kernels.ROW.WEIGHT_GRAD],
                               row[kernels.ROW.UNIT_BEARING], row[kernels.ROW.DISTANCE],
                               row[kernels.ROW.PROJECTOR].reshape(3, 3))
        a, b = weight_sum_row(pair, velocity, s_w, gamma, n)
        rows.append(a)
        lower.append(b)
    for other in others:
        if np.linalg.norm(np.subtract(position, other)) <= radius:
            a, b = collision_row(np.array(position), np.array(other), delta, gain)
            rows.append(a)
            lower.append(b)
    rows += [np.array(a) for a in envelope_rows]
    lower += list(envelope_lower)
    if bound > 0.0:
        lower = [robust_lower_bound(b, tuple(a), bound) for a, b in zip(rows, lower, strict=True)]
    return np.array(rows).reshape(-1, 3), np.array(lower)


@pytest.mark.parametrize("rule", ["equal", "weighted"])
@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(1, 3), n_others=st.integers(0, 8),
       n_envelope=st.integers(0, 4), bound=st.sampled_from([0.0, 0.1, 0.2]))
def test_the_qp_rows_are_the_rows_of_the_readable_functions(rule, seed, m, n_others,
                                                            n_envelope, bound) -> None:
    """``kernels.qp_rows`` on the agent's inputs (the barrier kernel's rows of M targets,
    others near and far) gives the rows the readable functions give, in the agent's order,
    with either share of the localization condition (the weight sums S_w span below and
    above the drone's own weight, so k = w/S_w and k = 1 both occur)."""
    rng = np.random.default_rng(seed)
    drone = rng.normal(size=3) + np.array([0.0, 0.0, 3.0])
    estimates, velocities = rng.normal(size=(m, 6)), rng.normal(size=(m, 3))
    gramians = np.array([_gramian(rng.uniform(0.01, 3.0, 3), rng.uniform(0, 6, 3))
                         for _ in range(m)])
    means = np.array([_gramian(rng.uniform(0.0, 1.0, 3), rng.uniform(0, 6, 3))
                      for _ in range(m)])
    n_agents, forgetting, epsilon, exponent, info_gain = 4, 0.5, 0.05, -10.0, 1.3
    terms = kernels.perception_barrier_rows(
        drone, estimates, velocities, gramians.reshape(-1), means.reshape(-1),
        _constants(n_agents, forgetting, epsilon, exponent, info_gain))
    pairs = [perception_terms(drone, estimates[r, :3], PARAMS) for r in range(m)]
    barriers = [localization_barrier(gramians[r], means[r], pairs[r], velocities[r],
                                     n_agents=n_agents, forgetting=forgetting, epsilon=epsilon,
                                     exponent=exponent, info_gain=info_gain)
                for r in range(m)]
    weight_sums = rng.uniform(0.0, 4.0, m).tolist()
    position = drone.tolist()
    others = (drone + rng.normal(scale=1.5, size=(n_others, 3))).tolist()
    envelope_rows = [tuple(a) for a in rng.normal(size=(n_envelope, 3)).tolist()]
    envelope_lower = rng.normal(size=n_envelope).tolist()
    constants = _row_constants(float(n_agents), gain=1.2, bound=bound, rule=rule)
    columns, lower = kernels.qp_rows(terms, velocities, weight_sums, position, others,
                                     envelope_rows, envelope_lower,
                                     kernels.qp_row_constants(constants))
    rows, readable_lower = _readable_rows(terms, velocities, weight_sums, position, others,
                                          envelope_rows, envelope_lower, constants, barriers)
    assert len(lower) == rows.shape[0] and len(columns) == 3 * len(lower)
    np.testing.assert_array_equal(np.array(columns).reshape(3, -1).T, rows)
    np.testing.assert_allclose(lower[m:], readable_lower[m:], rtol=1e-12, atol=1e-12)
    # The localization bounds: the two barrier forms agree to round-off of the terms' scales
    # (test_perception_barrier_equals_localization_barrier); share·(c + ψ1) and d_i = −L_gi ψ1·v̂.
    for r, (b, pair) in enumerate(zip(barriers, pairs, strict=True)):
        share = localization_share(rule, pair.weight, weight_sums[r], n_agents)
        lie_scale = info_gain * float(np.sum(b.smooth_min.eigen_gradient)) * (
            float(np.linalg.norm(pair.weight_grad_drone)) + 2.0 * pair.weight / pair.distance_m)
        _close(lower[r], readable_lower[r],
               max(abs(readable_lower[r]), share * abs(b.coupling), share * abs(b.psi1),
                   share * b.lambda_bar, lie_scale * float(np.linalg.norm(velocities[r]))))
        if rule == "equal" and bound == 0.0:  # 1/N: the barrier kernel's bound as it is
            assert lower[r] == terms[r, kernels.ROW.LOWER]


def test_weighted_shares_put_the_condition_on_the_drones_that_see_the_target() -> None:
    """Three drones, w = (1, 0, 0), S_w = 1 at each: the first drone's localization row
    carries the whole condition −(c + ψ1) (3.27 with k = 1), the others' none (k = 0), and
    the rows add up to the centralized condition (3.28 = 3.21); equal shares give each a
    third of it."""
    n, combined = 3, -0.6  # c + ψ1 < 0: the swarm must gain information
    weights = (1.0, 0.0, 0.0)
    assert [localization_share("weighted", w, 1.0, n) for w in weights] == [1.0, 0.0, 0.0]
    assert [localization_share("equal", w, 1.0, n) for w in weights] == [1 / 3] * 3
    rng = np.random.default_rng(7)
    lie_g = [rng.normal(size=3) if w > 0 else np.zeros(3) for w in weights]  # w = 0: no gradient
    velocity = np.array([[0.4, -0.2, 0.1]])
    for rule, expected in (("weighted", [1.0, 0.0, 0.0]), ("equal", [1 / 3] * 3)):
        parts = []
        for w, a in zip(weights, lie_g, strict=True):
            row = np.zeros((1, kernels.ROW_SIZE))
            row[0, kernels.ROW.WEIGHT] = w
            row[0, kernels.ROW.LIE_G] = a
            drift = -float(a @ velocity[0])  # d_i = −L_gi ψ1·v̂
            row[0, kernels.ROW.LOWER] = -combined / n - drift  # the barrier kernel's 1/N bound
            _, lower = kernels.qp_rows(row, velocity, [1.0], [0.0, 0.0, 3.0], [], [], [],
                                       kernels.qp_row_constants(_row_constants(
                                           float(n), gamma=0.5, radius_m=3.0, rule=rule)))
            parts.append(lower[0] + drift)  # what the row asks of L_gi ψ1·(u_i − v̂)
        np.testing.assert_allclose(parts, [-k * combined for k in expected], rtol=1e-15,
                                   atol=1e-16)
        assert sum(parts) == pytest.approx(-combined, rel=1e-15)


def test_a_drone_exactly_at_the_collision_radius_has_a_row_and_one_beyond_has_none() -> None:
    terms = kernels.perception_barrier_rows(
        np.array([0.0, 0.0, 3.0]), np.zeros((1, 6)), np.zeros((1, 3)), np.eye(3).reshape(-1),
        np.zeros(9), _constants(4, 0.5, 0.05, -10.0, 1.3))
    beside = [1.5, 0.0, 3.0]
    beyond = [math.nextafter(1.5, 2.0), 0.0, 3.0]
    columns, lower = kernels.qp_rows(terms, np.zeros((1, 3)), [1.0], [0.0, 0.0, 3.0],
                                     [beyond, beside, beyond], [], [],
                                     kernels.qp_row_constants(_row_constants(4.0)))
    assert len(lower) == 3  # localization, weight sum, the one at R_ca
    assert columns[2::3] == [-3.0, 0.0, 0.0]  # x, y, z of the collision row: 2(p_i − p_j)
    assert lower[2] == -0.5 * (1.5**2 - 0.5**2)


_SHARE_AT = kernels.QP_ROW_CONSTANTS.index("localization_share")
_ROW_CONSTANTS = kernels.qp_row_constants(_row_constants(1.0))


@pytest.mark.parametrize(("change", "error", "message"), [
    ({"terms": np.zeros((1, 23))}, ValueError, "terms"),
    ({"velocities": np.zeros((2, 3))}, ValueError, "velocities"),
    ({"weight_sums": np.zeros(1)}, TypeError, "weight_sums, others and envelope_rows"),
    ({"others": [[1.0, 2.0, 3.0], [1.0, 2.0]]}, ValueError, r"others\[1\]: expected 3"),
    ({"others": [[1.0, 2.0, "3"]]}, TypeError, r"others\[0\]\[2\]: expected a float"),
    ({"envelope_lower": [0.0]}, ValueError, "envelope_lower: expected 0 floats"),
    ({"constants": _ROW_CONSTANTS[1:]}, ValueError,
     f"constants: expected {len(_ROW_CONSTANTS)} floats"),
    ({"constants": [*_ROW_CONSTANTS[:_SHARE_AT], 0.5, *_ROW_CONSTANTS[_SHARE_AT + 1:]]},
     ValueError, rf"constants\[{_SHARE_AT}\] \(the localization share\) must be 0 \(1/N\) "
                 r"or 1 \(weighted\), got 0.5"),
])
def test_qp_rows_names_what_it_was_given_wrong(change, error, message) -> None:
    args = {"terms": np.zeros((1, kernels.ROW_SIZE)), "velocities": np.zeros((1, 3)),
            "weight_sums": [1.0], "position": [0.0, 0.0, 3.0], "others": [],
            "envelope_rows": [], "envelope_lower": [], "constants": _ROW_CONSTANTS} | change
    with pytest.raises(error, match=message) as err:
        kernels.qp_rows(*args.values())
    assert "\n" not in str(err.value)


# -- derivatives on the agent's path ------------------------------------------------------------

FD_STEP_M = 1e-6
FD_ATOL = 1e-8  # the budget of test_barrier.py / test_perception.py (finite_difference)


@pytest.mark.parametrize(("distance_regime", "cosine_regime"), REGIMES)
def test_the_weight_gradient_the_agent_uses_is_the_weights_derivative(
        distance_regime: str, cosine_regime: str) -> None:
    """∂w/∂p_i of the kernel = central differences of the kernel's own w."""
    rng = np.random.default_rng(700 + REGIMES.index((distance_regime, cosine_regime)))
    for _ in range(5):
        target = rng.uniform(-1.0, 1.0, 3)
        drone = random_drone_in_regime(rng, target, distance_regime, cosine_regime)
        numeric = central_gradient(
            lambda p, t=target: kernels.perception(p, t, PARAMS).weight, drone, FD_STEP_M)
        np.testing.assert_allclose(kernels.perception(drone, target, PARAMS).weight_grad_drone,
                                   numeric, rtol=0, atol=FD_ATOL)


@pytest.mark.parametrize("exponent", [-4.0, -10.0, -30.0])
@pytest.mark.parametrize(("distance_regime", "cosine_regime"), REGIMES)
def test_the_barrier_gradient_the_agent_uses_is_the_derivative_of_psi1(
        distance_regime: str, cosine_regime: str, exponent: float) -> None:
    """L_gi ψ1 of the kernel = ∂ψ1/∂p_i at a fixed Gramian, where the drone's own term
    w(p_i)Π̂(p_i) enters the mean s = (wΠ̂ + Σ others)/N of the Gramian's model rate,
    ψ1 = ⟨Γ, −ρG + bNs⟩ + λ̄ − ε: so ∂ψ1/∂p_i = b∂⟨Γ, wΠ̂⟩/∂p_i, the row the QP gets. ψ1 itself
    is the kernel's at every probe."""
    rng = np.random.default_rng(800 + 10 * REGIMES.index((distance_regime, cosine_regime))
                                - int(exponent))
    n_agents, forgetting, epsilon, info_gain = 4, 0.5, 0.05, 1.3
    constants = _constants(n_agents, forgetting, epsilon, exponent, info_gain)
    for _ in range(3):
        target = rng.uniform(-1.0, 1.0, 3)
        drone = random_drone_in_regime(rng, target, distance_regime, cosine_regime)
        rotation = special_ortho_group.rvs(3, random_state=rng)
        gramian = rotation @ np.diag(rng.uniform(0.05, 3.0, 3)) @ rotation.T
        others = sum(t.weight * np.reshape(t.projector, (3, 3)) for t in (
            kernels.perception(random_drone_in_regime(rng, target, "nominal", "on_axis"),
                               target, PARAMS)
            for _ in range(n_agents - 1)))

        def barrier_at(p: np.ndarray, t=target, rest=others, g=gramian):
            own = kernels.perception(p, t, PARAMS)
            mean = (own.weight * np.reshape(own.projector, (3, 3)) + rest) / n_agents
            return kernels.barrier(p, t, np.zeros(3), g, mean, constants)[1]

        numeric = central_gradient(lambda p: barrier_at(p).psi1, drone, FD_STEP_M)
        np.testing.assert_allclose(barrier_at(drone).lie_g, numeric, rtol=0, atol=FD_ATOL)


# -- the ICF's local steps (SPEC §5) ----------------------------------------------------------


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
    """``icf.StackedFilter`` (the kernel: pinv(W⁺) = V⁻¹/N from one Cholesky factor) against
    ``posterior``, ``posterior_covariance`` and ``predict`` (2.8-2.11, 2.21-2.22) target by
    target, with and without the communicated velocity; W⁻ symmetric exactly."""
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
        assert np.array_equal(fast[2][r], fast[2][r].T)
        covariance = icf.posterior_covariance(info)
        _close(fast[3][r], covariance, condition * float(np.max(np.abs(covariance))))


@pytest.mark.parametrize("bad", [np.diag([1.0, 2.0, 3.0, 0.0, 0.0, 0.0]),  # velocity never seen
                                 np.diag([1.0, 2.0, 3.0, 4.0, 5.0, -1e-9]),
                                 np.full((6, 6), math.nan)])
def test_stacked_filter_takes_the_readable_path_for_an_information_not_positive_definite(
        bad) -> None:
    """One V not positive definite (or not finite): every target goes through
    ``posterior``/``predict`` with the SVD pseudo-inverse, so the result is theirs exactly."""
    rng = np.random.default_rng(5)
    information = _spd_stack(rng, 2, 6, 10.0)
    information[1] = bad
    vector = rng.normal(size=(2, 6))
    transition = icf.transition_matrix("double_integrator", 0.02)
    assert kernels.filter_stack(information, vector, transition, 0.01, 3) is None
    if np.isnan(bad).any():
        return  # the readable path's SVD does not converge on NaN: nothing to compare
    fast = icf.StackedFilter(transition, 0.01, 3, 0.02)(information, vector)
    for r in range(2):
        state, info = icf.posterior(information[r], vector[r], 3)
        prior_state, prior_info = icf.predict(state, info, transition, 0.01)
        assert np.array_equal(fast[0][r], state) and np.array_equal(fast[1][r], prior_state)
        assert np.array_equal(fast[2][r], prior_info)
        assert np.array_equal(fast[3][r], icf.posterior_covariance(info))


# -- what the kernels refuse --------------------------------------------------------------------


@pytest.mark.parametrize(("args", "error", "message"), [
    ((np.zeros(3, dtype=np.float32), np.ones(3)), TypeError, "drone: expected float64"),
    ((np.zeros(4), np.ones(3)), ValueError, "drone: expected 3 float64 values, got 4"),
    ((np.zeros(6)[::2], np.ones(3)), TypeError, "drone: expected a C-contiguous"),
    ((np.zeros(3), [1.0, 2.0, 3.0]), TypeError, "target: expected a C-contiguous float64"),
])
def test_a_bad_buffer_gets_a_one_line_error(args, error, message) -> None:
    constants = np.array(kernels.perception_constants(PARAMS))
    with pytest.raises(error, match=message):
        kernels._kernels.perception(*args, constants, np.empty(kernels.PERCEPTION_SIZE))
    with pytest.raises(TypeError, match="out: expected a writable"):
        out = np.empty(kernels.PERCEPTION_SIZE)
        out.flags.writeable = False
        kernels._kernels.perception(np.zeros(3), np.ones(3), constants, out)


def test_the_filter_refuses_mismatched_stacks() -> None:
    transition = icf.transition_matrix("double_integrator", 0.02)
    outputs = (np.empty((2, 6)), np.empty((2, 6)), np.empty((2, 6, 6)), np.empty((2, 6, 6)))
    with pytest.raises(ValueError, match="information: expected 72 float64 values, got 36"):
        kernels._kernels.filter_stack(np.eye(6), np.ones((2, 6)), transition, 0.01, 3.0,
                                      *outputs)
    with pytest.raises(ValueError, match="transition must be n x n"):
        kernels._kernels.filter_stack(np.eye(6), np.ones(6), np.ones(5), 0.01, 3.0, *outputs)


# -- the layouts the module exports -------------------------------------------------------------


def _tile(fields: tuple[tuple[str, int, int], ...], size: int) -> bool:
    """The fields lie one after the other from 0 to ``size``, none empty."""
    starts = [start for _, start, _ in fields]
    return (starts == [0, *(stop for _, _, stop in fields[:-1])] and fields[-1][2] == size
            and all(stop > start for _, start, stop in fields))


# ``kernels.ROW``'s attributes and the fields they stand for.
_ROW_NAMES = {"WEIGHT": "weight", "WEIGHT_GRAD": "weight_grad_drone",
              "UNIT_BEARING": "unit_bearing", "DISTANCE": "distance_m", "PROJECTOR": "projector",
              "LAMBDA_BAR": "lambda_bar", "PSI0": "psi0", "PSI1": "psi1", "LIE_G": "lie_g",
              "LOWER": "lower_bound"}


def test_the_row_layout_is_the_compiled_modules() -> None:
    """``ROW`` and the named tuples read a row where the C module says each field is: the
    fields tile the row (perception terms first), are named as the named tuples' fields, and
    every one is an attribute of ``ROW`` at the module's place."""
    fields = kernels._kernels.ROW_FIELDS
    assert kernels.ROW_FIELDS is fields and _tile(fields, kernels.ROW_SIZE)
    assert [name for name, _, _ in fields] == [*kernels.PerceptionScalars._fields,
                                               *kernels.BarrierScalars._fields]
    assert fields[len(kernels.PerceptionScalars._fields)][1] == kernels.PERCEPTION_SIZE
    at = {name: (start, stop) for name, start, stop in fields}
    row = {name: value for name, value in vars(kernels.ROW).items() if name.isupper()}
    assert row.keys() == _ROW_NAMES.keys() and set(_ROW_NAMES.values()) == at.keys()
    for name, value in row.items():
        start, stop = at[_ROW_NAMES[name]]
        assert value == (start if stop - start == 1 else slice(start, stop)), name


def test_the_smooth_min_layout_is_the_compiled_modules() -> None:
    fields = kernels._kernels.SMOOTH_MIN_FIELDS
    assert kernels.SMOOTH_MIN_FIELDS is fields
    assert _tile(fields, kernels._kernels.SMOOTH_MIN_SIZE)
    assert tuple(name for name, _, _ in fields) == kernels.SmoothMinScalars._fields


def test_the_constants_go_where_the_compiled_module_names_them() -> None:
    """``perception_constants``, ``barrier_constants`` and ``qp_row_constants`` put each
    value at the position the C module names for it (distinct values, read back by name)."""
    assert kernels.PERCEPTION_CONSTANTS is kernels._kernels.PERCEPTION_CONSTANTS
    params = PerceptionParams(d_min_th_m=1.5, d_max_th_m=7.0, sigma_dmin_sq_m2=0.05,
                              sigma_dmax_sq_m2=2.0, alpha_th_deg=30.0, sigma_beta_sq=0.02)
    by_name = {name: getattr(params, name) for name in kernels.PERCEPTION_CONSTANTS}
    assert len(set(by_name.values())) == len(by_name) == 6
    assert dict(zip(kernels.PERCEPTION_CONSTANTS, kernels.perception_constants(params),
                    strict=True)) == by_name
    assert kernels.BARRIER_CONSTANTS is kernels._kernels.BARRIER_CONSTANTS
    assert len(kernels.BARRIER_CONSTANTS) == kernels._kernels.CONSTANTS_SIZE
    constants = kernels.barrier_constants(params, n_agents=5, forgetting=0.25, epsilon=0.07,
                                          exponent=-9.0, info_gain=1.75)
    assert dict(zip(kernels.BARRIER_CONSTANTS, constants.tolist(), strict=True)) == by_name | {
        "n_agents": 5.0, "forgetting": 0.25, "epsilon": 0.07, "exponent": -9.0,
        "info_gain": 1.75, "eigenvalue_floor": EIGENVALUE_FLOOR,
        "near_repeated_log_gap": NEAR_REPEATED_LOG_GAP}
    assert kernels.QP_ROW_CONSTANTS is kernels._kernels.QP_ROW_CONSTANTS
    values = dict(zip(kernels.QP_ROW_CONSTANTS, [2.0, 3.0, 5.0, 7.0, 11.0, 13.0, 1.0],
                      strict=True))
    assert kernels.qp_row_constants(values) == [values[n] for n in kernels.QP_ROW_CONSTANTS]
    with pytest.raises(VigilError, match=r"missing \['gamma'\]"):
        kernels.qp_row_constants({k: v for k, v in values.items() if k != "gamma"})


def test_the_localization_shares_are_the_compiled_modules_and_the_configs() -> None:
    assert list(kernels.LOCALIZATION_SHARES) == list(get_args(LocalizationShare))
    codes = {name: float(code) for code, name in enumerate(kernels._kernels.LOCALIZATION_SHARES)}
    assert codes == kernels.LOCALIZATION_SHARES


def test_the_packed_icf_pair_is_the_compiled_modules() -> None:
    """A consensus message packs the ICF pair as ``initial_information`` writes it."""
    assert kernels.ICF_PAIR is kernels._kernels.ICF_PAIR
    assert PAIR_NAMES is kernels.ICF_PAIR
    layout = message_layout(2, 6, False)
    assert [name for name, _, _, _ in layout] == list(kernels.ICF_PAIR)
    sizes = {"information": 2 * 6 * 6, "information_vector": 2 * 6}
    assert [(start, stop - start) for _, _, start, stop in layout] == [
        (0, sizes[kernels.ICF_PAIR[0]]), (sizes[kernels.ICF_PAIR[0]], sizes[kernels.ICF_PAIR[1]])]


def test_consensus_step_reads_each_part_of_z_where_z_starts_says() -> None:
    """An index at ``z_starts``' start of each part (plus an offset) reads that part's value:
    the state, the disagreement, the input, the 0."""
    assert kernels.CONSENSUS_STEP_Z is kernels._kernels.CONSENSUS_STEP_Z
    n, n_u = 4, 3
    x, d, u = np.arange(1.0, 5.0), np.arange(10.0, 14.0), [100.0, 200.0, 300.0]
    starts = kernels.z_starts(n, n_u)
    assert sorted(starts.values()) == [0, n, 2 * n, 2 * n + n_u]
    for part, values in (("state", x.tolist()), ("disagreement", d.tolist()), ("input", u),
                         ("zero", [0.0])):
        at = [min(i, len(values) - 1) for i in range(n)]  # each of the part's values
        index = np.array([[starts[part] + k for k in at]], dtype=np.intp)
        out = np.empty(n)
        kernels.consensus_step(x, d, u, index, np.ones((1, n)), out)
        assert out.tolist() == [values[k] for k in at], part
    with pytest.raises(ValueError, match=r"an index lies outside z \(12 floats\)"):
        kernels.consensus_step(x, d, u, np.full((1, n), 12, dtype=np.intp), np.ones((1, n)),
                               np.empty(n))
