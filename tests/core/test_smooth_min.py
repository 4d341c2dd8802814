"""Smooth minimum eigenvalue λ̄(G) = (Σ λ_k^p)^(1/p) and its derivatives (SPEC §7)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import logsumexp
from scipy.stats import special_ortho_group

from swarm.core.smooth_min import EIGENVALUE_FLOOR, inner, smooth_min_eigenvalue

from .finite_difference import central_derivative

EXPONENTS = [-4.0, -10.0, -30.0]


def _rotated(eigenvalues: list[float], seed: int) -> np.ndarray:
    rotation = special_ortho_group.rvs(3, random_state=seed)
    return rotation @ np.diag(eigenvalues) @ rotation.T


def _random_symmetric(rng: np.random.Generator) -> np.ndarray:
    """A symmetric direction with unit Frobenius norm."""
    a = rng.normal(size=(3, 3))
    h = a + a.T
    return h / np.linalg.norm(h)


def _log_space_value(eigenvalues: np.ndarray, p: float) -> float:
    """(Σ λ^p)^(1/p) evaluated as exp(logsumexp(p log λ)/p): no overflow for any p."""
    return float(np.exp(logsumexp(p * np.log(eigenvalues)) / p))


# Eigenvalue sets, each given as (label, eigenvalues). The clustered ones are where the
# single-eigenvalue Hessian fails and the divided differences θ_kl must take their limit.
SPECTRA = [
    ("spread", [0.5, 1.0, 2.0]),
    ("wide", [0.05, 0.9, 4.0]),
    ("gap 1e-6 at bottom", [1.0, 1.0 + 1e-6, 2.0]),
    ("gap 1e-9 at bottom", [1.0, 1.0 + 1e-9, 2.0]),
    ("gap 1e-9 at top", [0.3, 2.0, 2.0 + 2e-9]),
    ("repeated pair diag(a, a, b)", [0.7, 0.7, 1.9]),
    ("isotropic 2εI", [0.1, 0.1, 0.1]),
]


@pytest.mark.parametrize("p", EXPONENTS)
@pytest.mark.parametrize(("label", "eigenvalues"), SPECTRA)
def test_value_matches_the_naive_formula(label: str, eigenvalues: list[float], p: float) -> None:
    """λ̄ equals (Σ λ_k^p)^(1/p) computed directly from eigvalsh (moderate λ: no overflow)."""
    gramian = _rotated(eigenvalues, seed=len(label))
    lam = np.linalg.eigvalsh(gramian)
    naive = float(np.sum(lam**p)) ** (1.0 / p)
    assert smooth_min_eigenvalue(gramian, p).value == pytest.approx(naive, rel=1e-13)


def test_value_does_not_overflow_for_tiny_eigenvalues_and_large_exponent() -> None:
    """λ ~ 1e-6 with p = −60 overflows λ^p (1e360); the scaled form matches log-space."""
    lam = np.array([1e-6, 3e-6, 2e-5])
    sm = smooth_min_eigenvalue(np.diag(lam), -60.0)
    assert np.isfinite(sm.value)
    assert sm.value == pytest.approx(_log_space_value(lam, -60.0), rel=1e-13)
    assert np.all(np.isfinite(sm.gradient))


def test_non_positive_eigenvalues_are_clipped_to_the_floor() -> None:
    """A singular or indefinite G (SPEC §7 guard, default p) gives a finite λ̄ ≤ the floor
    and finite derivatives."""
    for gramian in (np.diag([0.0, 1.0, 2.0]), np.diag([-0.3, 0.5, 1.0])):
        sm = smooth_min_eigenvalue(gramian, -10.0)
        assert np.all(sm.eigenvalues >= EIGENVALUE_FLOOR)
        assert 0.0 < sm.value <= EIGENVALUE_FLOOR
        assert np.all(np.isfinite(sm.gradient))
        assert np.isfinite(sm.second_derivative(np.ones((3, 3))))


spd_matrices = st.tuples(
    st.lists(st.floats(1e-3, 1e3), min_size=3, max_size=3),
    st.integers(0, 2**31 - 1),
).map(lambda drawn: _rotated(drawn[0], seed=drawn[1]))


@settings(deadline=None, max_examples=150, derandomize=True)
@given(spd_matrices, st.sampled_from([-1.0, -4.0, -10.0, -30.0, -60.0]))
def test_value_is_a_lower_bound_within_three_to_the_one_over_p(gramian: np.ndarray,
                                                               p: float) -> None:
    """3^(1/p) λ_min ≤ λ̄ ≤ λ_min (SPEC §7).

    Against the eigenvalues λ̄ was computed from, the bound holds to a few ulps (1e-13
    relative). Those eigenvalues agree with eigvalsh to the backward-stable level of
    1e-14·λ_max (absolute: a tiny λ_min next to a large λ_max is only known that well).
    """
    sm = smooth_min_eigenvalue(gramian, p)
    reference = np.linalg.eigvalsh(gramian)
    np.testing.assert_allclose(sm.eigenvalues, reference, rtol=0, atol=1e-14 * reference[-1])
    lam_min = sm.eigenvalues[0]
    assert sm.value <= lam_min * (1.0 + 1e-13)
    assert sm.value >= 3.0 ** (1.0 / p) * lam_min * (1.0 - 1e-13)


@settings(deadline=None, max_examples=100, derandomize=True)
@given(spd_matrices, st.sampled_from(EXPONENTS))
def test_gradient_is_symmetric_and_satisfies_euler_homogeneity(gramian: np.ndarray,
                                                               p: float) -> None:
    """Γ is symmetric with eigenvalues g_k ∈ (0, 1], and ⟨Γ, G⟩ = λ̄ (λ̄ is 1-homogeneous)."""
    sm = smooth_min_eigenvalue(gramian, p)
    gamma = sm.gradient
    np.testing.assert_allclose(gamma, gamma.T, atol=1e-15)
    assert np.all(sm.eigen_gradient > 0.0)
    assert np.all(sm.eigen_gradient <= 1.0 + 1e-12)
    assert inner(gamma, gramian) == pytest.approx(sm.value, rel=1e-10)


@pytest.mark.parametrize("p", EXPONENTS)
@pytest.mark.parametrize(("label", "eigenvalues"), SPECTRA)
def test_gradient_matches_central_differences(label: str, eigenvalues: list[float],
                                              p: float) -> None:
    """⟨Γ, H⟩ equals (λ̄(G + hH) − λ̄(G − hH))/2h for random symmetric unit H.

    With h = 1e-5·λ_min the truncation h²·|D³λ̄|/6, |D³λ̄| ≲ 2(1 − p)²/λ_min², is ≤ 3e-7 for
    p = −30 and round-off ε·λ̄/h ≈ 2e-11 (λ̄ ≈ λ_min); the observed error is ≤ 5e-8. The
    tolerance 1e-6 is relative and absolute: |⟨Γ, H⟩| ≤ 1 because 0 < g_k ≤ 1 and ‖H‖ = 1.
    """
    rng = np.random.default_rng(len(label) + int(-p))
    gramian = _rotated(eigenvalues, seed=len(label))
    step = 1e-5 * min(eigenvalues)
    for _ in range(5):
        direction = _random_symmetric(rng)
        analytic = inner(smooth_min_eigenvalue(gramian, p).gradient, direction)
        numeric = central_derivative(
            lambda t, h=direction: smooth_min_eigenvalue(gramian + t * h, p).value, step)
        assert analytic == pytest.approx(numeric, rel=1e-6, abs=1e-6)


@pytest.mark.parametrize("p", EXPONENTS)
@pytest.mark.parametrize(("label", "eigenvalues"), SPECTRA)
def test_second_derivative_matches_differences_of_the_gradient(label: str,
                                                               eigenvalues: list[float],
                                                               p: float) -> None:
    """D²λ̄[H, H] equals d/dt ⟨Γ(G + tH), H⟩ at t = 0 by central differences.

    This includes nearly repeated (relative gap 1e-6, 1e-9) and exactly repeated eigenvalues,
    where the divided differences θ_kl must reach their limit without cancellation. Step
    h = 1e-5·λ_min; the natural scale of D²λ̄ is (1 − p)/λ_min, and truncation
    h²|D⁴λ̄|/6 ≲ 1e-10·(1 − p)³/λ_min³·λ_min² stays below 1e-6 of that scale for p = −30,
    while round-off is ε/h ≈ 2e-11/λ_min. The tolerance is 1e-6 relative plus 1e-7 of the scale.
    """
    rng = np.random.default_rng(1000 + len(label) + int(-p))
    gramian = _rotated(eigenvalues, seed=len(label))
    lam_min = min(eigenvalues)
    step = 1e-5 * lam_min
    scale = (1.0 - p) / lam_min
    sm = smooth_min_eigenvalue(gramian, p)
    for _ in range(5):
        direction = _random_symmetric(rng)
        numeric = central_derivative(
            lambda t, h=direction: inner(smooth_min_eigenvalue(gramian + t * h, p).gradient, h),
            step)
        assert sm.second_derivative(direction) == pytest.approx(numeric, rel=1e-6,
                                                                abs=1e-7 * scale)


@pytest.mark.parametrize("p", EXPONENTS)
def test_second_derivative_matches_second_central_difference_of_the_value(p: float) -> None:
    """Independent check: D²λ̄[H, H] ≈ (λ̄(G+hH) − 2λ̄(G) + λ̄(G−hH))/h² (at G = 2εI too).

    The second difference loses more to round-off (ε·λ̄/h² ≈ 2e-8·λ̄/λ_min² for h = 1e-4·λ_min)
    and truncation (h²|D⁴λ̄|/12), so the tolerance is looser: 1e-4 relative plus 1e-5 of the
    curvature scale (1 − p)/λ_min.
    """
    rng = np.random.default_rng(int(-p))
    for eigenvalues in ([0.1, 0.1, 0.1], [0.4, 0.4 + 4e-7, 1.3], [0.2, 0.6, 3.0]):
        gramian = _rotated(eigenvalues, seed=3)
        lam_min = min(eigenvalues)
        step = 1e-4 * lam_min
        direction = _random_symmetric(rng)

        def value(t: float, g: np.ndarray = gramian, h: np.ndarray = direction) -> float:
            return smooth_min_eigenvalue(g + t * h, p).value

        numeric = (value(step) - 2.0 * value(0.0) + value(-step)) / step**2
        analytic = smooth_min_eigenvalue(gramian, p).second_derivative(direction)
        assert analytic == pytest.approx(numeric, rel=1e-4, abs=1e-5 * (1.0 - p) / lam_min)


@settings(deadline=None, max_examples=100, derandomize=True)
@given(spd_matrices, st.sampled_from(EXPONENTS))
def test_second_derivative_vanishes_along_g_and_is_concave(gramian: np.ndarray,
                                                           p: float) -> None:
    """λ̄ is 1-homogeneous, so D²λ̄[G, G] = 0; it is concave (p < 0), so D²λ̄[H, H] ≤ 0.

    Both need the cross terms ∂²f/∂λ_k∂λ_l: without them D²λ̄[G, G] = (p − 1)Σ g_kλ_k ≠ 0.
    Tolerance: 1e-9 of |p − 1|·‖G‖²/λ_min, the size of the cancelling terms.
    """
    sm = smooth_min_eigenvalue(gramian, p)
    lam = np.linalg.eigvalsh(gramian)
    scale = (1.0 - p) * float(np.sum(lam**2)) / lam[0]
    assert abs(sm.second_derivative(gramian)) <= 1e-9 * scale
    rng = np.random.default_rng(0)
    for _ in range(3):
        assert sm.second_derivative(_random_symmetric(rng)) <= 1e-9 * (1.0 - p) / lam[0]


def _reference_second_derivative(eigenvalues: np.ndarray, direction: np.ndarray,
                                 p: float) -> float:
    """D²λ̄[H, H] for G = diag(λ), evaluated without cancellation, in log space.

    With shares σ_k = λ_k^p/Σλ^p: g_k = (λ_k/f)^(p−1), ∂²f/∂λ_k∂λ_l = (1−p)g_kg_l/f for
    k ≠ l, ∂²f/∂λ_k² = (p−1)(g_k/λ_k)Σ_{m≠k}σ_m, and θ_kl = (g_k − g_l)/(λ_k − λ_l) taken
    literally (accurate for the well separated eigenvalues used below).
    """
    lam = np.asarray(eigenvalues, dtype=float)
    log_total = logsumexp(p * np.log(lam))
    value = float(np.exp(log_total / p))
    shares = np.exp(p * np.log(lam) - log_total)
    g = np.exp((p - 1.0) * np.log(lam / value))
    hessian = (1.0 - p) * np.outer(g, g) / value
    for k in range(3):
        hessian[k, k] = (p - 1.0) * g[k] / lam[k] * (np.sum(shares) - shares[k])
    diag = np.diag(direction)
    total = float(diag @ hessian @ diag)
    for k in range(3):
        for m in range(3):
            if k != m:
                total += (g[k] - g[m]) / (lam[k] - lam[m]) * direction[k, m] ** 2
    return total


@pytest.mark.parametrize(
    ("p", "eigenvalues"),
    [
        (-10.0, [1e-9, 1.0, 1e3]),
        (-30.0, [2e-9, 0.5, 10.0]),
        (-60.0, [1e-3, 1.0, 5.0]),
        (-60.0, [1e-4, 1.0, 20.0]),  # (1−p)·log(cond) > 709: expm1 would overflow here
        (-30.0, [1e-9, 1.0, 20.0]),
    ],
)
def test_second_derivative_is_finite_for_ill_conditioned_gramians(p: float,
                                                                  eigenvalues: list[float]) -> None:
    """Allowed exponents (params: p ∈ [−60, −1]) with a Gramian that lost information in one
    direction (λ_min down to the 1e-9 floor): θ is symmetric and finite and D²λ̄ matches a
    cancellation-free reference. The implementation forms ∂²f/∂λ_k² as the difference of two
    terms of size |p − 1|/λ_k, which costs ~ε·|p − 1|/λ_min absolute; tolerance 50× that."""
    gramian = np.diag(eigenvalues)
    direction = np.ones((3, 3))
    sm = smooth_min_eigenvalue(gramian, p)
    assert np.all(np.isfinite(sm.divided_differences))
    np.testing.assert_allclose(sm.divided_differences, sm.divided_differences.T, rtol=1e-9)
    expected = _reference_second_derivative(np.array(eigenvalues), direction, p)
    assert sm.second_derivative(direction) == pytest.approx(
        expected, rel=1e-9, abs=50 * 2.2e-16 * (1.0 - p) / min(eigenvalues))


# -- what mutation testing found untested (issue 46, point 2; docs/mutation.md) ------------


def test_the_diagonal_of_the_divided_differences_is_their_repeated_limit() -> None:
    """θ_kk = (p − 1) g_k/λ_k is what θ_kl tends to as λ_l → λ_k."""
    sm = smooth_min_eigenvalue(np.diag([2.0, 2.0 + 1e-9, 5.0]), -10.0)
    theta = sm.divided_differences
    assert theta[0, 0] == pytest.approx(-11.0 * sm.eigen_gradient[0] / 2.0, rel=1e-12)
    assert theta[0, 1] == pytest.approx(theta[0, 0], rel=1e-6)
    assert theta[1, 1] == pytest.approx(theta[0, 1], rel=1e-6)
