"""SPEC invariants checked on a finished run, and the per-target / per-drone summary figures."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from swarm.reference import RunRecord

SENSING_WEIGHT = 0.1  # a drone "senses" a target when w > this (issue 4's definition)


@dataclass(frozen=True)
class Violation:
    invariant: str
    detail: str

    def __str__(self) -> str:
        return f"{self.invariant}: {self.detail}"


@dataclass(frozen=True)
class TargetSummary:
    target: int
    min_lambda_bar_margin: float  # min over drones and steps after start of λ̄ − ε
    time_below_epsilon_s: float  # time after start during which some copy had λ̄ < ε
    min_true_lambda_margin: float  # min of λ_min(true G) − ε after start
    min_measured_lambda: float  # min of λ_min(measured G) after start
    final_position_error_m: float  # max over drones at the last step
    rms_position_error_m: float  # over drones and all steps after start
    drones_sensing_final: int


@dataclass(frozen=True)
class DroneSummary:
    drone: int
    final_speed_m_s: float
    final_weights: tuple[float, ...]
    idle_final: bool  # w ≤ SENSING_WEIGHT for every target at the end
    qp_fallbacks: int
    mean_step_us: float
    p99_step_us: float
    final_bearing_error: float | None


def _start_index(record: RunRecord) -> int:
    return int(np.ceil(record.config.control.start_s / record.config.scenario.dt_s - 1e-9))


def summarize_targets(record: RunRecord) -> list[TargetSummary]:
    eps = record.config.gramian.epsilon
    dt = record.config.scenario.dt_s
    k0 = _start_index(record)
    errors = record.position_errors()
    out = []
    for r in range(record.target_positions_m.shape[1]):
        lam = record.lambda_bar[k0:, :, r]
        out.append(TargetSummary(
            target=r,
            min_lambda_bar_margin=float(lam.min() - eps),
            time_below_epsilon_s=float(np.any(lam < eps, axis=1).sum() * dt),
            min_true_lambda_margin=float(record.true_lambda_min[k0:, r].min() - eps),
            min_measured_lambda=float(record.measured_lambda_min[k0:, r].min()),
            final_position_error_m=float(errors[-1, :, r].max()),
            rms_position_error_m=float(np.sqrt(np.mean(errors[k0:, :, r] ** 2))),
            drones_sensing_final=int(np.sum(record.weights[-1, :, r] > SENSING_WEIGHT)),
        ))
    return out


def summarize_drones(record: RunRecord) -> list[DroneSummary]:
    out = []
    for i in range(record.drone_positions_m.shape[1]):
        weights = record.weights[-1, i]
        bearing_err = record.bearing_errors[-1, i]
        out.append(DroneSummary(
            drone=i,
            final_speed_m_s=float(np.linalg.norm(record.velocities_m_s[-1, i])),
            final_weights=tuple(float(w) for w in weights),
            idle_final=bool(np.all(weights <= SENSING_WEIGHT)),
            qp_fallbacks=int(record.qp_fallback[:, i].sum()),
            mean_step_us=float(record.step_us[:, i].mean()),
            p99_step_us=float(np.percentile(record.step_us[:, i], 99)),
            final_bearing_error=None if np.isnan(bearing_err) else float(bearing_err),
        ))
    return out


def check_invariants(record: RunRecord) -> list[Violation]:
    """SPEC invariants with the scenario's tolerances ([checks] of the config)."""
    cfg = record.config
    eps, tol = cfg.gramian.epsilon, cfg.checks.lambda_tolerance
    k0 = _start_index(record)
    violations: list[Violation] = []
    finite = all(np.all(np.isfinite(a)) for a in (
        record.drone_positions_m, record.velocities_m_s, record.estimates, record.lambda_bar))
    if not finite:
        violations.append(Violation("finite", "a position, command, estimate or λ̄ is NaN/inf"))
    for r in range(record.target_positions_m.shape[1]):
        lam = record.lambda_bar[k0:, :, r]
        if lam.size and lam.min() < eps - tol:
            k, i = np.unravel_index(int(np.argmin(lam)), lam.shape)
            violations.append(Violation(
                "lambda_bar",
                f"target {r}: drone {i} has λ̄ = {lam.min():.4f} < ε − tol = {eps - tol:.4f} "
                f"at t = {record.times_s[k0 + k]:.2f} s"))
    min_dist = record.min_pairwise_distance()
    floor = cfg.control.collision_distance_m - cfg.checks.collision_tolerance_m
    if min_dist < floor:
        violations.append(Violation(
            "collision", f"min pairwise distance {min_dist:.4f} m < Δ − tol = {floor:.4f} m"))
    u_max = cfg.control.u_max_m_s
    if np.abs(record.velocities_m_s).max(initial=0.0) > u_max + 1e-9:
        violations.append(Violation("velocity_bound", f"a command exceeds u_max = {u_max} m/s"))
    return violations
