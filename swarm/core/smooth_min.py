"""Smooth minimum eigenvalue λ̄(G) = (Σ_k λ_k^p)^(1/p), p < 0, and its derivatives (SPEC §7).

Evaluated in a scaled form so that no power overflows even for tiny eigenvalues and large |p|:
with f = λ̄, g_k = ∂f/∂λ_k = (λ_k/f)^(p−1) ∈ (0, 1].

The second derivative uses the divided-difference (Daleckii–Krein) form, whose off-diagonal
coefficients θ_kl = (g_k − g_l)/(λ_k − λ_l) are evaluated, for nearly repeated eigenvalues, as
``g_l/λ_l · expm1((p−1)t)/expm1(t)`` with ``t = log(λ_k/λ_l)``: exact in the limit
λ_k → λ_l instead of dividing two vanishing differences.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swarm.core.projector import Mat3, Vec3

EIGENVALUE_FLOOR = 1e-9  # eigenvalues are clipped to this before powers (SPEC §7 guard)
# |log(λ_k/λ_l)| below which θ_kl uses the expm1 form; there |(p−1)·t| ≤ 0.061 for p ≥ −60.
NEAR_REPEATED_LOG_GAP = 1e-3


@dataclass(frozen=True)
class SmoothMin:
    """λ̄ of one Gramian with what its first and second derivatives need."""

    value: float  # λ̄
    eigenvalues: Vec3  # λ_k (clipped), ascending
    eigenvectors: Mat3  # columns v_k
    eigen_gradient: Vec3  # g_k = ∂f/∂λ_k
    eigen_hessian: Mat3  # ∂²f/∂λ_k∂λ_l
    divided_differences: Mat3  # θ_kl for k ≠ l (diagonal holds the k = l limit)

    @property
    def gradient(self) -> Mat3:
        """Γ = ∂λ̄/∂G = V diag(g) Vᵀ (SPEC §7, thesis B.8)."""
        v = self.eigenvectors
        return (v * self.eigen_gradient) @ v.T

    def second_derivative(self, direction: Mat3) -> float:
        """D²λ̄[H, H] for a symmetric direction H (SPEC §7)."""
        v = self.eigenvectors
        rotated = v.T @ direction @ v
        diag = rotated.diagonal()
        theta = self.divided_differences
        # Σ_{k≠l} θ_kl H̃_kl² over the three symmetric pairs, each counted twice.
        off = 2.0 * (theta[0, 1] * rotated[0, 1] ** 2 + theta[0, 2] * rotated[0, 2] ** 2
                     + theta[1, 2] * rotated[1, 2] ** 2)
        return float(diag @ self.eigen_hessian @ diag + off)


def smooth_min_eigenvalue(gramian: Mat3, exponent: float) -> SmoothMin:
    """λ̄(G) with its eigen-decomposition and derivative coefficients (SPEC §7, thesis 3.31)."""
    p = exponent
    raw, vectors = np.linalg.eigh(gramian)
    lam = np.maximum(raw, EIGENVALUE_FLOOR)
    lam_min = lam[0]
    value = lam_min * float(np.sum((lam / lam_min) ** p)) ** (1.0 / p)
    g = (lam / value) ** (p - 1.0)
    hessian = (1.0 - p) * np.outer(g, g) / value
    hessian[np.diag_indices(3)] += (p - 1.0) * g / lam
    theta = np.empty((3, 3))
    for k in range(3):
        theta[k, k] = (p - 1.0) * g[k] / lam[k]  # the k = l limit
    for k, j in ((0, 1), (0, 2), (1, 2)):
        theta[k, j] = theta[j, k] = _divided_difference(lam, g, k, j, p)
    return SmoothMin(value, lam, vectors, g, hessian, theta)


def _divided_difference(lam: Vec3, g: Vec3, k: int, j: int, p: float) -> float:
    """θ_kj = (g_k − g_j)/(λ_k − λ_j), symmetric in k, j (see ``divided_difference``)."""
    return divided_difference(float(lam[k]), float(lam[j]), float(g[k]), float(g[j]), p)


def divided_difference(lam_k: float, lam_l: float, g_k: float, g_l: float, p: float) -> float:
    """θ_kl = (g_k − g_l)/(λ_k − λ_l) on plain floats, symmetric in k, l.

    Well-separated pairs: the plain quotient of bounded g's is accurate and cannot overflow.
    Near-repeated pairs: g_l/λ_l · expm1((p−1)t)/expm1(t), t = log(λ_k/λ_l), whose arguments
    stay small there and whose limit t → 0 is exactly p − 1.
    """
    t = math.log(lam_k / lam_l)
    if abs(t) >= NEAR_REPEATED_LOG_GAP:
        return (g_k - g_l) / (lam_k - lam_l)
    ratio = p - 1.0 if t == 0.0 else math.expm1((p - 1.0) * t) / math.expm1(t)
    return g_l / lam_l * ratio


def inner(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """⟨A, B⟩ = trace(AᵀB) (SPEC §8)."""
    return float(np.sum(a * b))
