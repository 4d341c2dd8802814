"""Smooth minimum eigenvalue λ̄(G) = (Σ_k λ_k^p)^(1/p), p < 0, and its derivatives (SPEC §7).

Evaluated in a scaled form so that no power overflows even for tiny eigenvalues and large |p|:
with f = λ̄, g_k = ∂f/∂λ_k = (λ_k/f)^(p−1) ∈ (0, 1].

The second derivative uses the divided-difference (Daleckii–Krein) form, whose off-diagonal
coefficients θ_kl = (g_k − g_l)/(λ_k − λ_l) are evaluated, for nearly repeated eigenvalues, as
``g_l/λ_l · expm1((p−1)t)/expm1(t)`` with ``t = log(λ_k/λ_l)``: exact in the limit
λ_k → λ_l instead of dividing two vanishing differences.
"""

from __future__ import annotations

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
        diag = np.diag(rotated)
        off = rotated * rotated
        np.fill_diagonal(off, 0.0)
        return float(diag @ self.eigen_hessian @ diag + np.sum(self.divided_differences * off))


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
    log_ratio = np.log(lam[:, None] / lam[None, :])
    near = np.abs(log_ratio) < NEAR_REPEATED_LOG_GAP
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        # Well-separated pairs: the plain quotient of bounded g's is exact enough and cannot
        # overflow; near-repeated pairs: the expm1 form, whose arguments stay small there.
        direct = (g[:, None] - g[None, :]) / (lam[:, None] - lam[None, :])
        ratio = np.expm1((p - 1.0) * log_ratio) / np.expm1(log_ratio)
        ratio = np.where(log_ratio == 0.0, p - 1.0, ratio)
        theta = np.where(near, (g / lam)[None, :] * ratio, direct)
    return SmoothMin(value, lam, vectors, g, hessian, theta)


def inner(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """⟨A, B⟩ = trace(AᵀB) (SPEC §8)."""
    return float(np.sum(a * b))
