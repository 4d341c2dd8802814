"""Control barrier rows of the local QP (SPEC §8, thesis 3.20-3.25, 3.32-3.36, 4.1-4.2).

Each row is returned as ``coefficients · u_i ≥ lower_bound`` (plus a slack where the QP has
one), computed only from drone i's local copies: its Gramian copy G_ir, its consensus estimate
s_ir of (1/N)Σ_j w_jr Π̂_jr, its estimate (p̂_ir, v̂_ir) and its own position.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from swarm.core.params import LocalizationShare
from swarm.core.perception import PerceptionTerms, weighted_projector_derivative
from swarm.core.projector import Mat3, Vec3
from swarm.core.smooth_min import SmoothMin, inner, smooth_min_eigenvalue


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

    def shared_lower_bound(self, share: float) -> float:
        """Right-hand side of L_gi ψ1·u + δ ≥ −k_i(c + ψ1) − d_i: (3.27) with drone i's share
        k_i of the condition (``localization_share``); k_i = 1/N is ``lower_bound``."""
        return -share * (self.coupling + self.psi1) - self.drift


def localization_share(rule: LocalizationShare, weight: float, weight_sum_estimate: float,
                       n_agents: int) -> float:
    """Drone i's share k_ir of target r's localization condition (thesis 3.27-3.28).

    The local rows (3.27) add up to the centralized condition (3.21) when the k_i are a
    convex combination, k_i ≥ 0 and Σ_i k_i = 1: summed over the drones they give
    Σ_i (L_gi ψ1·u_i + d_i) ≥ −(Σ_i k_i)(c + ψ1) (3.28). The thesis takes k_i = 1/N and says
    other choices are possible.

    ``"equal"``: 1/N, SPEC §8 (3.32). A drone that does not see the target (w_ir ≈ 0, so
    L_gi ψ1 ≈ 0) cannot meet its share with its velocity; in the relaxed QP it buys it with a
    slack at the cost K_δ·max(w_ir, w_floor), and nobody takes the part it dropped.

    ``"weighted"``: w_ir / max(S_wr, w_ir), with S_wr = N·s_wr drone i's consensus estimate of
    Σ_j w_jr (the one the weight-sum row 3.34-3.36 uses); 0 when w_ir = 0, and 1 when the
    estimate is below drone i's own weight. The condition goes to the drones that see the
    target, in proportion to how well. With S_wr the exact sum, Σ_i k_ir = 1 and (3.28) is
    (3.21). Each drone divides by its own estimate, so Σ_i k_ir = 1 holds only up to the
    consensus error on S_w: the rows then add up to −(Σ_i k_ir)(c + ψ1), which implies (3.21)
    when c + ψ1 ≥ 0 and Σ_i k_ir ≤ 1 or when c + ψ1 < 0 and Σ_i k_ir ≥ 1, and otherwise falls
    short of it by |1 − Σ_i k_ir|·|c + ψ1|.
    """
    if rule == "equal":
        return 1.0 / n_agents
    if not weight > 0.0:
        return 0.0
    return weight / (weight_sum_estimate if weight_sum_estimate > weight else weight)


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
