"""SPEC invariants checked on a finished run, and the per-target / per-drone summary figures.

A record read back from a realtime or truncated recording has NaN where a message never
arrived. Every figure here is a NaN-aware reduction over the samples that are present, and
says how many were missing; "final" means a drone's last step with a sample. The invariant
checks never let a NaN pass: a NaN inside a sample that did arrive is a ``finite`` violation,
and an invariant with no sample at all to check is reported as not held ("not checked").
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from swarm.core.safety import envelope_margins
from swarm.runs.record import RunRecord

SENSING_WEIGHT = 0.1  # a drone "senses" a target when w > this (issue 4's definition)

BoolArray = NDArray[np.bool_]
FloatArray = NDArray[np.float64]


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
    final_position_error_m: float  # max over drones of each drone's last error
    rms_position_error_m: float  # over drones and all steps after start
    drones_sensing_final: int  # drones whose last weight for this target is > SENSING_WEIGHT
    missing_samples: int = 0  # drone-steps without a λ̄ for this target (never received)


@dataclass(frozen=True)
class DroneSummary:
    drone: int
    final_speed_m_s: float
    final_weights: tuple[float, ...]
    idle_final: bool  # w ≤ SENSING_WEIGHT for every target at the end
    qp_fallbacks: int
    mean_step_us: float
    p99_step_us: float
    final_bearing_error: float | None  # None without a formation task
    missing_samples: int = 0  # steps whose telemetry from this drone never arrived


@dataclass(frozen=True)
class Coverage:
    """How much of a record is present (a lockstep or in-process record is complete)."""

    steps: int
    drone_steps: int  # steps × drones
    missing_telemetry: int  # drone-steps whose telemetry never arrived
    missing_truth: int  # steps without ground truth (drone and target positions)
    missing_per_drone: tuple[int, ...]

    @property
    def complete(self) -> bool:
        return self.missing_telemetry == 0 and self.missing_truth == 0


def _quiet_nan(function: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """Call a nan-reduction; an all-NaN slice gives NaN without a RuntimeWarning."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return function(*args, **kwargs)


def nanmin(values: FloatArray) -> float:
    """Smallest non-NaN value; NaN when there is none (also for an empty array)."""
    if values.size == 0:
        return float("nan")
    return float(_quiet_nan(np.nanmin, values))


def nanmax(values: FloatArray) -> float:
    """Largest non-NaN value; NaN when there is none (also for an empty array)."""
    if values.size == 0:
        return float("nan")
    return float(_quiet_nan(np.nanmax, values))


def start_index(record: RunRecord) -> int:
    """First step at or after ``control.start_s`` (the QP runs from here on)."""
    return int(np.ceil(record.config.control.start_s / record.config.scenario.dt_s - 1e-9))


_start_index = start_index  # the name this module used before


def telemetry_missing(record: RunRecord) -> BoolArray:
    """(K, N): drone i's telemetry of step k never arrived (its command and λ̄ are all NaN)."""
    return (np.isnan(record.velocities_m_s).all(axis=-1)
            & np.isnan(record.lambda_bar).all(axis=-1))


def truth_missing(record: RunRecord) -> BoolArray:
    """(K,): no ground truth for step k (every drone and target position is NaN)."""
    return (np.isnan(record.drone_positions_m).all(axis=(1, 2))
            & np.isnan(record.target_positions_m).all(axis=(1, 2)))


def coverage(record: RunRecord) -> Coverage:
    missing = telemetry_missing(record)
    return Coverage(
        steps=record.n_steps,
        drone_steps=int(missing.size),
        missing_telemetry=int(missing.sum()),
        missing_truth=int(truth_missing(record).sum()),
        missing_per_drone=tuple(int(v) for v in missing.sum(axis=0)),
    )


def last_present(values: FloatArray) -> int | None:
    """Index of the last step (axis 0) where ``values`` has a finite entry, None if none."""
    if values.size == 0:
        return None
    finite = np.isfinite(values.reshape(values.shape[0], -1)).any(axis=1)
    indices = np.flatnonzero(finite)
    return int(indices[-1]) if indices.size else None


def final_values(series: FloatArray) -> FloatArray:
    """Per drone, the value at its last step with a sample: (K, N, ...) → (N, ...)."""
    out = np.full(series.shape[1:], np.nan)
    for i in range(series.shape[1]):
        k = last_present(series[:, i])
        if k is not None:
            out[i] = series[k, i]
    return out


def min_pairwise_distance(record: RunRecord) -> float:
    """Smallest distance between two drones over the run, NaN-aware [m]; NaN if unknown.

    One pass per drone instead of a (K, N, N) array: the memory stays O(K·N).
    """
    p = record.drone_positions_m
    best = float("nan")
    for i in range(p.shape[1] - 1):
        dist = np.linalg.norm(p[:, i + 1:] - p[:, i:i + 1], axis=-1)
        best = float(np.fmin(best, nanmin(dist)))
    return best


def max_abs_velocity(record: RunRecord) -> float:
    """Largest |u_k| (one axis of one command) over the run [m/s], the box bound's quantity."""
    return nanmax(np.abs(record.velocities_m_s))


def summarize_targets(record: RunRecord) -> list[TargetSummary]:
    eps = record.config.gramian.epsilon
    dt = record.config.scenario.dt_s
    k0 = start_index(record)
    errors = record.position_errors()
    final_errors = final_values(errors)  # (N, M)
    final_weights = final_values(record.weights)  # (N, M)
    out = []
    for r in range(record.target_positions_m.shape[1]):
        lam = record.lambda_bar[k0:, :, r]
        after = errors[k0:, :, r]
        out.append(TargetSummary(
            target=r,
            min_lambda_bar_margin=nanmin(lam) - eps,
            time_below_epsilon_s=float(np.any(lam < eps, axis=1).sum() * dt),
            min_true_lambda_margin=nanmin(record.true_lambda_min[k0:, r]) - eps,
            min_measured_lambda=nanmin(record.measured_lambda_min[k0:, r]),
            final_position_error_m=nanmax(final_errors[:, r]),
            rms_position_error_m=float(np.sqrt(_quiet_nan(np.nanmean, after**2)))
            if after.size else float("nan"),
            drones_sensing_final=int(np.sum(final_weights[:, r] > SENSING_WEIGHT)),
            missing_samples=int(np.isnan(record.lambda_bar[:, :, r]).sum()),
        ))
    return out


def summarize_drones(record: RunRecord) -> list[DroneSummary]:
    formation = record.config.control.task == "bearing_formation"
    missing = telemetry_missing(record)
    out = []
    for i in range(record.drone_positions_m.shape[1]):
        k = last_present(record.velocities_m_s[:, i])
        weights = record.weights[k, i] if k is not None else np.full(
            record.weights.shape[2], np.nan)
        speed = float(np.linalg.norm(record.velocities_m_s[k, i])) if k is not None else np.nan
        bearing_k = last_present(record.bearing_errors[:, i]) if formation else None
        step_us = record.step_us[:, i]
        has_timing = bool(np.isfinite(step_us).any())
        out.append(DroneSummary(
            drone=i,
            final_speed_m_s=speed,
            final_weights=tuple(float(w) for w in weights),
            idle_final=bool(np.all(weights <= SENSING_WEIGHT)),
            qp_fallbacks=int(record.qp_fallback[:, i].sum()),
            mean_step_us=float(np.nanmean(step_us)) if has_timing else float("nan"),
            p99_step_us=float(np.nanpercentile(step_us, 99)) if has_timing else float("nan"),
            final_bearing_error=(None if bearing_k is None
                                 else float(record.bearing_errors[bearing_k, i])),
            missing_samples=int(missing[:, i].sum()),
        ))
    return out


def _check_finite(record: RunRecord) -> list[Violation]:
    """Present samples must be finite; ±inf is never a missing sample."""
    present = ~telemetry_missing(record)
    telemetry = (record.velocities_m_s, record.estimates, record.lambda_bar)
    bad = [int((np.any(~np.isfinite(a), axis=tuple(range(2, a.ndim))) & present).sum())
           for a in telemetry]
    infinite = any(np.isinf(a).any() for a in (record.drone_positions_m,
                                                record.target_positions_m))
    if sum(bad) == 0 and not infinite:
        return []
    return [Violation("finite", f"a position, command, estimate or λ̄ is NaN/inf "
                                f"({sum(bad)} received samples non-finite"
                                f"{', a position is inf' if infinite else ''})")]


def _check_lambda_bar(record: RunRecord) -> list[Violation]:
    cfg = record.config
    eps, tol = cfg.gramian.epsilon, cfg.checks.lambda_tolerance
    k0 = start_index(record)
    violations = []
    for r in range(record.target_positions_m.shape[1]):
        lam = record.lambda_bar[k0:, :, r]
        if not np.isfinite(lam).any():
            violations.append(Violation(
                "lambda_bar", f"target {r}: not checked: no λ̄ sample after control.start_s = "
                              f"{cfg.control.start_s} s"))
            continue
        low = nanmin(lam)
        if low < eps - tol:
            k, i = np.unravel_index(int(np.nanargmin(lam)), lam.shape)
            violations.append(Violation(
                "lambda_bar",
                f"target {r}: drone {i} has λ̄ = {low:.4f} < ε − tol = {eps - tol:.4f} "
                f"at t = {record.times_s[k0 + k]:.2f} s"))
    return violations


def _check_collision(record: RunRecord) -> list[Violation]:
    cfg = record.config
    min_dist = min_pairwise_distance(record)
    floor = cfg.control.collision_distance_m - cfg.checks.collision_tolerance_m
    if np.isnan(min_dist):
        return [Violation("collision", "not checked: no step with two drone positions")]
    if min_dist < floor:
        return [Violation(
            "collision", f"min pairwise distance {min_dist:.4f} m < Δ − tol = {floor:.4f} m")]
    return []


def envelope_margin_series(record: RunRecord) -> dict[str, FloatArray]:
    """Each drone's distance to each kind of boundary of the [safety] envelope at every step
    (``swarm.core.safety.envelope_margins``; negative: outside), (K, N) per kind, NaN where
    a position is missing; {} without an envelope."""
    envelope = record.config.safety.params
    if envelope.empty:
        return {}
    positions = record.drone_positions_m
    k, n = positions.shape[:2]
    kinds = envelope_margins((0.0, 0.0, 0.0), envelope)
    series = {kind: np.full((k, n), np.nan) for kind in kinds}
    for step, drone in zip(*np.nonzero(np.isfinite(positions).all(axis=2)), strict=True):
        for kind, margin in envelope_margins(tuple(positions[step, drone].tolist()),
                                             envelope).items():
            series[kind][step, drone] = margin
    return series


def min_envelope_margins(record: RunRecord) -> dict[str, float]:
    """The smallest distance of any drone to each kind of boundary over the run [m]."""
    return {kind: nanmin(values) for kind, values in envelope_margin_series(record).items()}


def _check_envelope(record: RunRecord) -> list[Violation]:
    margins = min_envelope_margins(record)
    tolerance = record.config.checks.envelope_tolerance_m
    out = []
    for kind, margin in margins.items():
        if np.isnan(margin):
            out.append(Violation("envelope", f"{kind}: not checked: no drone position"))
        elif margin < -tolerance:
            out.append(Violation("envelope", f"a drone went {-margin:.4f} m beyond the "
                                             f"{kind} (tolerance {tolerance} m)"))
    return out


def _check_velocity_bound(record: RunRecord) -> list[Violation]:
    u_max = record.config.control.u_max_m_s
    peak = max_abs_velocity(record)
    if np.isnan(peak):
        return [Violation("velocity_bound", "not checked: no command in the record")]
    if peak > u_max + 1e-9:
        return [Violation("velocity_bound",
                          f"a command reaches |u_k| = {peak:.4f} m/s > u_max = {u_max} m/s")]
    return []


def check_invariants(record: RunRecord) -> list[Violation]:
    """SPEC invariants with the scenario's tolerances ([checks] of the config).

    Checked on the samples present; an invariant with nothing to check is a violation.
    """
    return [*_check_finite(record), *_check_lambda_bar(record), *_check_collision(record),
            *_check_envelope(record), *_check_velocity_bound(record)]
