"""Parameters of the numerical core, as frozen dataclasses that validate themselves.

Every field carries its unit in the name or in a ``# [unit]`` comment. Validation happens in
``__post_init__`` so that a wrong value is refused where it is created, whether it came from a
config file (``swarm.scenario.config`` turns the ``ValueError`` into a one-line message naming
the key) or from code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal


def require(condition: bool, field: str, reason: str, value: object) -> None:
    """Raise ``ValueError("<field> <reason> (got <value>)")`` unless ``condition`` holds."""
    if not condition:
        raise ValueError(f"{field} {reason} (got {value!r})")


def require_finite_positive(field: str, value: float) -> None:
    require(math.isfinite(value) and value > 0, field, "must be a finite number > 0", value)


def require_finite(field: str, value: float) -> None:
    require(math.isfinite(value), field, "must be a finite number", value)


@dataclass(frozen=True)
class PerceptionParams:
    """Perception-awareness weight shape (SPEC §3, thesis 3.6-3.7, Fig. 3.1)."""

    d_min_th_m: float = 1.0  # D_m^th: below it the weight decays [m]
    d_max_th_m: float = 6.0  # D_M^th: above it the weight decays [m]
    sigma_dmin_sq_m2: float = 0.04  # σ_Dm² [m²]
    sigma_dmax_sq_m2: float = 1.8  # σ_DM² [m²]
    alpha_th_deg: float = 35.0  # α_M^th: off-axis angle where the weight starts to decay [deg]
    sigma_beta_sq: float = 0.015  # σ_β² [dimensionless, cosine units squared]

    def __post_init__(self) -> None:
        require_finite_positive("d_min_th_m", self.d_min_th_m)
        require_finite_positive("sigma_dmin_sq_m2", self.sigma_dmin_sq_m2)
        require_finite_positive("sigma_dmax_sq_m2", self.sigma_dmax_sq_m2)
        require_finite_positive("sigma_beta_sq", self.sigma_beta_sq)
        require(
            math.isfinite(self.d_max_th_m) and self.d_max_th_m > self.d_min_th_m,
            "d_max_th_m",
            "must be a finite number > d_min_th_m",
            self.d_max_th_m,
        )
        require(
            math.isfinite(self.alpha_th_deg) and 0 < self.alpha_th_deg < 90,
            "alpha_th_deg",
            "must lie in (0, 90) degrees",
            self.alpha_th_deg,
        )

    @property
    def cos_alpha_th(self) -> float:
        return math.cos(math.radians(self.alpha_th_deg))


@dataclass(frozen=True)
class ConsensusGains:
    """Gains of one PI dynamic average consensus estimator (SPEC §6, thesis 3.30, Table 4.2)."""

    zeta: float  # ζ: low-pass rate of the tracked average [1/s]
    kp: float  # K_p: proportional coupling [1/s]
    ki: float  # K_i: integral coupling [1/s]

    def __post_init__(self) -> None:
        require_finite_positive("zeta", self.zeta)
        require_finite_positive("kp", self.kp)
        require_finite_positive("ki", self.ki)


TargetModel = Literal["double_integrator", "single_integrator"]
ConsensusWeighting = Literal["metropolis", "laplacian"]


@dataclass(frozen=True)
class EstimationParams:
    """Information Consensus Filter (SPEC §5, thesis Algorithm 1 and 2.17-2.22)."""

    # the targets' motion model: "double_integrator" (position and velocity estimated) or
    # "single_integrator" (position only, 2.17-2.22)
    model: TargetModel = "double_integrator"
    consensus_rounds: int = 1  # K, consensus iterations per step
    process_noise: float = 0.01  # Q = q·I [m² or (m/s)² per step]
    info_gain: float = 1.0  # b [dimensionless]
    # a_ij of the ICF consensus: "metropolis" (Metropolis-Hastings, local and doubly
    # stochastic) or "laplacian" (the thesis' ε-Laplacian form, a_ij = laplacian_step)
    consensus_weights: ConsensusWeighting = "metropolis"
    laplacian_step: float = 0.2  # ε of the Laplacian form, used only with "laplacian" [1]
    initial_offset_m: float = 0.5  # initial guess = truth + U(-x, x) per axis [m]

    def __post_init__(self) -> None:
        require(self.model in ("double_integrator", "single_integrator"), "model",
                "must be 'double_integrator' or 'single_integrator'", self.model)
        require(isinstance(self.consensus_rounds, int) and 1 <= self.consensus_rounds <= 50,
                "consensus_rounds", "must be an integer in [1, 50]", self.consensus_rounds)
        require_finite_positive("process_noise", self.process_noise)
        require_finite_positive("info_gain", self.info_gain)
        require(self.consensus_weights in ("metropolis", "laplacian"), "consensus_weights",
                "must be 'metropolis' or 'laplacian'", self.consensus_weights)
        require_finite_positive("laplacian_step", self.laplacian_step)
        require(math.isfinite(self.initial_offset_m) and self.initial_offset_m >= 0,
                "initial_offset_m", "must be a finite number >= 0", self.initial_offset_m)


@dataclass(frozen=True)
class GramianParams:
    """Weighted observability Gramian with forgetting and its smooth minimum (SPEC §6-§7)."""

    forgetting: float = 0.6  # ρ [1/s]
    epsilon: float = 0.05  # ε, information threshold on λ_min [s]
    smooth_min_exponent: float = -10.0  # p of λ̄ = (Σ λ_k^p)^(1/p) [1]
    consensus_gain: float = 1.0  # gain of Σ_j (G_j − G_i) [1/s]
    # PI consensus on the weighted projectors wΠ̂ (3.30, Table 4.2)
    projector_consensus: ConsensusGains = ConsensusGains(zeta=4.0, kp=5.0, ki=3.0)
    # PI consensus on the perception weights w (3.30, Table 4.2)
    weight_consensus: ConsensusGains = ConsensusGains(zeta=8.0, kp=12.0, ki=6.0)

    def __post_init__(self) -> None:
        require_finite_positive("forgetting", self.forgetting)
        require_finite_positive("epsilon", self.epsilon)
        require(math.isfinite(self.smooth_min_exponent) and -60 <= self.smooth_min_exponent <= -1,
                "smooth_min_exponent", "must lie in [-60, -1]", self.smooth_min_exponent)
        require_finite_positive("consensus_gain", self.consensus_gain)


QpMode = Literal["hard", "relaxed"]
QpSolverName = Literal["daqp", "piqp"]  # swarm.core.qp.QP_SOLVERS
LocalizationShare = Literal["equal", "weighted"]  # swarm.core.barrier.localization_share
NominalTask = Literal["zero", "bearing_formation"]


@dataclass(frozen=True)
class ControlParams:
    """Local QP and its constraints (SPEC §8-§10, thesis 3.32-3.37, 4.1-4.2)."""

    start_s: float = 1.0  # localization rows from here; only safety rows before [s]
    qp: QpMode = "relaxed"  # "hard" = 3.37 (no slacks), "relaxed" = 3.36
    # The QP's solver: "daqp" (dual active set, exact; the default) or "piqp" (proximal
    # interior point, the design's); swarm.core.qp_daqp, swarm.core.qp_piqp.
    qp_solver: QpSolverName = "daqp"
    # Drone i's share k_ir of the localization condition (thesis 3.27-3.28): "equal" is
    # k = 1/N (SPEC §8, 3.32; the default), "weighted" is k = w_ir / max(S_wr, w_ir)
    # (swarm.core.barrier.localization_share)
    localization_share: LocalizationShare = "equal"
    gamma: float = 0.5  # γ, lower bound on Σ_i w_ir [1]
    slack_weight: float = 1e6  # K_δ [1]
    weight_floor: float = 1e-3  # w_floor in K_δ·max(w, w_floor) keeps the QP strictly convex [1]
    u_max_m_s: float = 3.0  # box bound on every velocity component [m/s]
    collision_distance_m: float = 0.5  # Δ, minimum inter-drone distance [m]
    collision_radius_m: float = 3.0  # R_ca, drones closer than this get a collision row [m]
    collision_gain: float = 1.0  # α_ca of the collision CBF [1/s]
    task: NominalTask = "zero"  # the nominal input u_d: "zero" (hover) or "bearing_formation"
    formation_gain: float = 1.0  # k_f of the bearing-only formation law [m/s]
    # ē, a bound on the vehicle's tracking error ‖ṗ_i − u_i‖: every barrier row a·u ≥ b is
    # tightened to a·u ≥ b + ē‖a‖ (barrier.robust_lower_bound); 0 = the thesis (ṗ = u) [m/s]
    tracking_error_bound_m_s: float = 0.0
    # Bound on the change of each component of u per step, |u_k − u_(k−1)| ≤ a·ΔT, as the
    # QP's box (qp.rate_limited_box); 0 = none (the thesis) [m/s²]
    command_accel_limit_m_s2: float = 0.0

    def __post_init__(self) -> None:
        require(math.isfinite(self.start_s) and self.start_s >= 0, "start_s",
                "must be a finite number >= 0", self.start_s)
        require(self.qp in ("hard", "relaxed"), "qp", "must be 'hard' or 'relaxed'", self.qp)
        require(self.qp_solver in ("daqp", "piqp"), "qp_solver", "must be 'daqp' or 'piqp'",
                self.qp_solver)
        require(self.localization_share in ("equal", "weighted"), "localization_share",
                "must be 'equal' or 'weighted'", self.localization_share)
        require_finite_positive("gamma", self.gamma)
        require_finite_positive("slack_weight", self.slack_weight)
        require(math.isfinite(self.weight_floor) and 0 < self.weight_floor <= 1, "weight_floor",
                "must lie in (0, 1]", self.weight_floor)
        require_finite_positive("u_max_m_s", self.u_max_m_s)
        require_finite_positive("collision_distance_m", self.collision_distance_m)
        require(math.isfinite(self.collision_radius_m)
                and self.collision_radius_m > self.collision_distance_m,
                "collision_radius_m", "must be a finite number > collision_distance_m",
                self.collision_radius_m)
        require_finite_positive("collision_gain", self.collision_gain)
        require(self.task in ("zero", "bearing_formation"), "task",
                "must be 'zero' or 'bearing_formation'", self.task)
        require_finite_positive("formation_gain", self.formation_gain)
        for name in ("tracking_error_bound_m_s", "command_accel_limit_m_s2"):
            value = getattr(self, name)
            require(math.isfinite(value) and value >= 0, name,
                    "must be a finite number >= 0 (0 = off)", value)
        require(self.tracking_error_bound_m_s < self.u_max_m_s, "tracking_error_bound_m_s",
                "must be below u_max_m_s", self.tracking_error_bound_m_s)
