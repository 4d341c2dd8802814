"""Control barrier rows of the local QP (SPEC §8, thesis 3.20-3.25, 3.32-3.36, 4.1-4.2).

Each row is returned as ``coefficients · u_i ≥ lower_bound`` (plus a slack where the QP has
one), computed only from drone i's local copies: its Gramian copy G_ir, its consensus estimate
s_ir of (1/N)Σ_j w_jr Π̂_jr, its estimate (p̂_ir, v̂_ir) and its own position.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from swarm.core.perception import PerceptionScalars, PerceptionTerms, weighted_projector_derivative
from swarm.core.projector import Mat3, Vec3
from swarm.core.smooth_min import SmoothMin, inner, smooth_min_eigenvalue, smooth_min_scalars


@dataclass(frozen=True)
class LocalizationBarrier:
    """HOCBF terms for one target at one drone (SPEC §8)."""

    smooth_min: SmoothMin
    psi0: float  # ψ0 = λ̄ − ε
    psi1: float  # ψ1 = ⟨Γ, Ġ⟩ + ψ0
    lie_g: Vec3  # L_gi ψ1, row 1×3
    drift: float  # d_i
    coupling: float  # c
    n_agents: int

    @property
    def lambda_bar(self) -> float:
        return self.smooth_min.value

    @property
    def lower_bound(self) -> float:
        """Right-hand side of L_gi ψ1·u + δ ≥ −(c + ψ1)/N − d_i (thesis 3.32)."""
        return -(self.coupling + self.psi1) / self.n_agents - self.drift


def gramian_rate_model(
    gramian: Mat3, projector_mean: Mat3, n_agents: int, forgetting: float, info_gain: float
) -> Mat3:
    """Ġ = −ρG + bN s, the model rate without the consensus term (SPEC §8)."""
    return -forgetting * gramian + (info_gain * n_agents) * projector_mean


def localization_barrier(
    gramian: Mat3,
    projector_mean: Mat3,
    terms: PerceptionTerms,
    target_velocity_estimate: Vec3,
    *,
    n_agents: int,
    forgetting: float,
    epsilon: float,
    exponent: float,
    info_gain: float,
) -> LocalizationBarrier:
    """ψ0, ψ1, L_gi ψ1, d_i and c for one target (SPEC §8, thesis 3.20-3.25).

    L_gi ψ1 = b[⟨Γ, ∂(wΠ̂)/∂p_i,k⟩]_k; d_i = b Σ_k ⟨Γ, ∂(wΠ̂)/∂p̂_k⟩ v̂_k = −L_gi ψ1·v̂;
    c = D²λ̄[Ġ, Ġ] + (1 − ρ)⟨Γ, Ġ⟩.
    """
    sm = smooth_min_eigenvalue(gramian, exponent)
    rate = gramian_rate_model(gramian, projector_mean, n_agents, forgetting, info_gain)
    gamma = sm.gradient
    along_rate = inner(gamma, rate)
    psi0 = sm.value - epsilon
    psi1 = along_rate + psi0
    d_weighted_projector = weighted_projector_derivative(terms)
    lie_g = info_gain * np.einsum("kab,ab->k", d_weighted_projector, gamma)
    drift = -float(lie_g @ target_velocity_estimate)
    coupling = sm.second_derivative(rate) + (1.0 - forgetting) * along_rate
    return LocalizationBarrier(sm, psi0, psi1, lie_g, drift, coupling, n_agents)


# (λ̄, ψ0, ψ1, L_gi ψ1, lower bound) of one target, as plain floats.
class BarrierScalars(NamedTuple):
    """What ``LocalizationBarrier`` gives the QP, as plain floats."""

    lambda_bar: float  # λ̄
    psi0: float  # ψ0 = λ̄ − ε
    psi1: float  # ψ1 = ⟨Γ, Ġ⟩ + ψ0
    lie_g: tuple[float, float, float]  # L_gi ψ1
    lower_bound: float  # −(c + ψ1)/N − d_i (3.32)


def localization_barrier_scalars(
    eigenvalues: tuple[float, float, float],
    eigenvectors: list[list[float]],
    projector_mean: list[float],
    terms: PerceptionScalars,
    target_velocity_estimate: tuple[float, float, float],
    *,
    n_agents: int,
    forgetting: float,
    epsilon: float,
    exponent: float,
    info_gain: float,
) -> BarrierScalars:
    """``localization_barrier`` on plain floats, from ``eigh`` of G done by the caller.

    ``eigenvalues``/``eigenvectors`` are ``np.linalg.eigh(G)`` (ascending, columns v_k) as
    lists, ``projector_mean`` s row-major, ``terms`` from
    ``perception_scalars``. The same quantities as ``localization_barrier`` (SPEC §7-§8),
    evaluated in the eigenbasis of G, where Γ = V diag(g) Vᵀ never needs forming:

    - H̃ = VᵀĠV = −ρ diag(λ) + bN VᵀsV (VᵀGV = diag(λ), the eigenvalues before clipping);
    - ⟨Γ, Ġ⟩ = Σ_k g_k H̃_kk;
    - with c_k = v_k·β̂: Γβ̂ = Σ_k g_k c_k v_k, ⟨Γ, Π̂⟩ = Σ_k g_k − β̂ᵀΓβ̂, and
      ⟨Γ, ∂Π̂/∂p_i,k⟩ = (1/d̂)(t_kᵀΓβ̂ + β̂ᵀΓt_k) = (2/d̂)(Π̂Γβ̂)_k, t_k = Π̂e_k (B.15),

    identities that hold exactly, so the results equal ``localization_barrier``'s up to
    round-off.
    """
    value, _, (g0, g1, g2), hess, theta = smooth_min_scalars(eigenvalues, exponent)
    (v00, v01, v02), (v10, v11, v12), (v20, v21, v22) = eigenvectors
    s00, s01, s02, s10, s11, s12, s20, s21, s22 = projector_mean
    # s v_l, then H̃ = Vᵀ Ġ V for k ≤ l, Ġ = −ρG + bN s (model rate, no consensus term).
    q00 = s00 * v00 + s01 * v10 + s02 * v20
    q10 = s10 * v00 + s11 * v10 + s12 * v20
    q20 = s20 * v00 + s21 * v10 + s22 * v20
    q01 = s00 * v01 + s01 * v11 + s02 * v21
    q11 = s10 * v01 + s11 * v11 + s12 * v21
    q21 = s20 * v01 + s21 * v11 + s22 * v21
    q02 = s00 * v02 + s01 * v12 + s02 * v22
    q12 = s10 * v02 + s11 * v12 + s12 * v22
    q22 = s20 * v02 + s21 * v12 + s22 * v22
    neg_rho, bn = -forgetting, info_gain * n_agents
    d0 = neg_rho * eigenvalues[0] + bn * (v00 * q00 + v10 * q10 + v20 * q20)
    d1 = neg_rho * eigenvalues[1] + bn * (v01 * q01 + v11 * q11 + v21 * q21)
    d2 = neg_rho * eigenvalues[2] + bn * (v02 * q02 + v12 * q12 + v22 * q22)
    o01 = bn * (v00 * q01 + v10 * q11 + v20 * q21)
    o02 = bn * (v00 * q02 + v10 * q12 + v20 * q22)
    o12 = bn * (v01 * q02 + v11 * q12 + v21 * q22)
    along_rate = g0 * d0 + g1 * d1 + g2 * d2  # ⟨Γ, Ġ⟩
    psi0 = value - epsilon
    psi1 = along_rate + psi0
    # L_gi ψ1 = b[∂w/∂p_i,k ⟨Γ, Π̂⟩ + (2w/d̂)(Π̂Γβ̂)_k].
    weight, grad, (bx, by, bz), distance, _ = terms
    c0 = v00 * bx + v10 * by + v20 * bz
    c1 = v01 * bx + v11 * by + v21 * bz
    c2 = v02 * bx + v12 * by + v22 * bz
    gc0, gc1, gc2 = g0 * c0, g1 * c1, g2 * c2
    beta_gamma_beta = gc0 * c0 + gc1 * c1 + gc2 * c2
    gamma_proj = (g0 + g1 + g2) - beta_gamma_beta
    scale = 2.0 * weight / distance
    lie_g = (
        info_gain * (grad[0] * gamma_proj
                     + scale * (v00 * gc0 + v01 * gc1 + v02 * gc2 - bx * beta_gamma_beta)),
        info_gain * (grad[1] * gamma_proj
                     + scale * (v10 * gc0 + v11 * gc1 + v12 * gc2 - by * beta_gamma_beta)),
        info_gain * (grad[2] * gamma_proj
                     + scale * (v20 * gc0 + v21 * gc1 + v22 * gc2 - bz * beta_gamma_beta)))
    vx, vy, vz = target_velocity_estimate
    drift = -(lie_g[0] * vx + lie_g[1] * vy + lie_g[2] * vz)
    # D²λ̄[Ġ, Ġ] (SPEC §7).
    h00, h11, h22, h01, h02, h12 = hess
    second = (h00 * d0 * d0 + h11 * d1 * d1 + h22 * d2 * d2
              + 2.0 * (h01 * d0 * d1 + h02 * d0 * d2 + h12 * d1 * d2)
              + 2.0 * (theta[0] * o01 * o01 + theta[1] * o02 * o02 + theta[2] * o12 * o12))
    coupling = second + (1.0 - forgetting) * along_rate
    lower = -(coupling + psi1) / n_agents - drift
    return BarrierScalars(value, psi0, psi1, lie_g, lower)


def weight_sum_row(
    terms: PerceptionTerms,
    target_velocity_estimate: Vec3,
    weight_sum_estimate: float,
    gamma: float,
    n_agents: int,
) -> tuple[Vec3, float]:
    """∂w/∂p_i·u + δw ≥ −(S_w − γ)/N − ∂w/∂p̂·v̂ (SPEC §8, thesis 3.34-3.36).

    Returns (coefficients, lower bound); ∂w/∂p̂ = −∂w/∂p_i.
    """
    grad = terms.weight_grad_drone
    lower = -(weight_sum_estimate - gamma) / n_agents + float(grad @ target_velocity_estimate)
    return grad, lower


def robust_lower_bound(lower: float, coefficients: tuple[float, float, float],
                       tracking_error_bound: float) -> float:
    """b + ē‖a‖: the bound of a row a·u ≥ b that must hold for the vehicle as flown.

    The barriers of SPEC §8 are conditions on the drone's velocity ṗ_i, written with ṗ_i = u_i
    (the thesis' single integrator). A real vehicle flies ṗ_i = u_i + e_i with a tracking
    error ‖e_i‖ ≤ ē. By Cauchy-Schwarz, a·(u + e) ≥ a·u − ē‖a‖, with equality at the worst
    error e = −ē a/‖a‖. Hence

        a·u ≥ b + ē‖a‖   ⇒   a·ṗ_i ≥ b   for every ‖ṗ_i − u_i‖ ≤ ē,

    the robust (constant disturbance bound) form of the input-to-state-safe barrier: each
    condition holds on the flown velocity, not only on the command. A slack, where the row
    has one, enters as before: a·u + δ ≥ b + ē‖a‖. ē = 0 is the thesis' row; an inactive row
    (a = 0) is unchanged.
    """
    a0, a1, a2 = coefficients
    return lower + tracking_error_bound * math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)


def collision_row(
    own_position: Vec3, other_position: Vec3, min_distance_m: float, gain: float
) -> tuple[Vec3, float]:
    """2(p_i − p_j)ᵀu_i ≥ −α_ca h_ij/2, h_ij = ‖p_i − p_j‖² − Δ² (SPEC §8, thesis 4.1-4.2).

    Each drone of a pair takes half of the centralized constraint, so the pair satisfies it
    when both do.
    """
    offset = own_position - other_position
    h = float(offset @ offset) - min_distance_m * min_distance_m
    return 2.0 * offset, -0.5 * gain * h
