"""SPEC invariants checked on a finished run, and the per-target / per-drone summary figures.

A record read back from a realtime or truncated recording has NaN where a message never
arrived. Every figure here is a NaN-aware reduction over the samples that are present, and
says how many were missing; "final" means a drone's last step with a sample. The invariant
checks never let a NaN pass: a NaN inside a sample that did arrive is a ``finite`` violation,
and an invariant with no sample at all to check is reported as not held ("not checked").
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from swarm.core.safety import envelope_margins
from swarm.runs.network import check_network
from swarm.runs.record import RunRecord
from swarm.runs.violation import Violation

SENSING_WEIGHT = 0.1  # a drone "senses" a target when its perception weight w > this

BoolArray = NDArray[np.bool_]
FloatArray = NDArray[np.float64]


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
    # max over steps after start of max_i λ̄_ir − min_i λ̄_ir: how far the drones' copies of
    # the Gramian disagree (consensus; 0 for one drone)
    lambda_copy_spread: float = float("nan")


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
    planned_steps: int = 0  # the mission's steps (scenario.duration_s / ΔT)

    @property
    def complete(self) -> bool:
        """Every sample of every step recorded."""
        return self.missing_telemetry == 0 and self.missing_truth == 0

    @property
    def cut_short(self) -> bool:
        """The record ends before the mission did (Ctrl-C, a crash, a killed launcher)."""
        return self.steps < self.planned_steps


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
    return (np.all(np.isnan(record.velocities_m_s), axis=-1)
            & np.all(np.isnan(record.lambda_bar), axis=-1))


def truth_missing(record: RunRecord) -> BoolArray:
    """(K,): no ground truth for step k (every drone and target position is NaN)."""
    return (np.all(np.isnan(record.drone_positions_m), axis=(1, 2))
            & np.all(np.isnan(record.target_positions_m), axis=(1, 2)))


def coverage(record: RunRecord) -> Coverage:
    missing = telemetry_missing(record)
    return Coverage(
        steps=record.n_steps,
        drone_steps=int(missing.size),
        missing_telemetry=int(missing.sum()),
        missing_truth=int(truth_missing(record).sum()),
        missing_per_drone=tuple(int(v) for v in missing.sum(axis=0)),
        planned_steps=record.config.n_steps,
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


# Floats of pairwise differences held at once by ``closest_pair_per_step`` (8 MiB): the
# memory stays O(K·N) plus this, whatever the number of pairs.
_PAIR_CHUNK_VALUES = 1 << 20


def closest_pair_per_step(positions: FloatArray) -> tuple[FloatArray, NDArray[np.intp]]:
    """For each step of (K, N, 3) positions, the smallest distance between two drones [m] and
    that pair (i < j), over every pair whose two positions are present: (K,) distances, NaN
    where no pair is, and (K, 2) ids, −1 there. Steps are taken in chunks so the (steps,
    pairs, 3) differences stay within ``_PAIR_CHUNK_VALUES`` floats."""
    k, n = positions.shape[:2]
    first, second = np.triu_indices(n, 1)
    distance = np.full(k, np.nan)
    pair = np.full((k, 2), -1, dtype=np.intp)
    if first.size == 0:
        return distance, pair
    chunk = max(1, _PAIR_CHUNK_VALUES // (3 * first.size))
    for start in range(0, k, chunk):
        p = positions[start:start + chunk]
        d = np.linalg.norm(p[:, first] - p[:, second], axis=-1)  # (C, P), NaN: a pair missing
        present = ~np.isnan(d)
        closest = np.argmin(np.where(present, d, np.inf), axis=1)
        rows = np.arange(d.shape[0])
        any_pair = present.any(axis=1)
        distance[start:start + chunk] = np.where(any_pair, d[rows, closest], np.nan)
        pair[start:start + chunk] = np.where(
            any_pair[:, None], np.stack((first[closest], second[closest]), axis=1), -1)
    return distance, pair


def min_pairwise_distance(record: RunRecord) -> float:
    """Smallest distance between two drones over the run, NaN-aware [m]; NaN if unknown."""
    return nanmin(closest_pair_per_step(record.drone_positions_m)[0])


def max_abs_velocity(record: RunRecord) -> float:
    """Largest |u_k| (one axis of one command) over the run [m/s], the box bound's quantity."""
    return nanmax(np.abs(record.velocities_m_s))


def copy_spread(copies: FloatArray) -> float:
    """The widest disagreement of the drones' copies at one step: the largest over the steps
    (K, N) of max − min over the drones, NaN samples left out; NaN when no step has one."""
    widths = _quiet_nan(np.nanmax, copies, axis=1) - _quiet_nan(np.nanmin, copies, axis=1)
    return nanmax(widths)


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
            lambda_copy_spread=copy_spread(lam),
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


@dataclass(frozen=True)
class _Crossing:
    """Where a series (K, X) went past its limit: the worst sample, the first step past it
    and how many steps were; ``subject(k, x)`` names column x at step k."""

    worst_step: int
    worst_column: int
    worst_value: float
    first_step: int
    first_column: int
    steps_beyond: int


def _crossing(values: FloatArray, limit: float, *, below: bool) -> _Crossing | None:
    """Where ``values`` (K, X) went below (``below``) or above ``limit``; None if nowhere.
    NaN samples (missing) are never past the limit; the worst is the farthest past it, the
    earliest such sample on a tie, and the first crossing the lowest column of the first
    step past it."""
    beyond = values < limit if below else values > limit
    if not beyond.any():
        return None
    distance_past = np.where(beyond, (limit - values) if below else (values - limit), -1.0)
    worst_step, worst_column = np.unravel_index(int(np.argmax(distance_past)), values.shape)
    steps = beyond.any(axis=1)
    first_step = int(np.argmax(steps))
    return _Crossing(int(worst_step), int(worst_column),
                     float(values[worst_step, worst_column]), first_step,
                     int(np.argmax(beyond[first_step])), int(steps.sum()))


def _by_drone(prefix: str) -> Callable[[int, int], str]:
    """A violation's subject at (step, drone): "<prefix>, drone <i>"."""
    return lambda _k, i: f"{prefix}, drone {i}"


def _violation(invariant: str, crossing: _Crossing, limit: float, record: RunRecord,
               subject: Callable[[int, int], str], what: str, when: str = "") -> Violation:
    """A ``Violation`` of ``crossing`` (steps counted from the record's first); ``what`` is
    the line's head (which, the value and the limit), ``when`` the words for past it."""
    times = record.times_s
    dt = record.config.scenario.dt_s
    worst_subject = subject(crossing.worst_step, crossing.worst_column)
    first_subject = subject(crossing.first_step, crossing.first_column)
    worst_t, first_t = float(times[crossing.worst_step]), float(times[crossing.first_step])
    beyond_s = crossing.steps_beyond * dt
    word = when or "past the limit"
    detail = (f"{what} at t = {worst_t:.2f} s; first {word} at t = {first_t:.2f} s "
              f"({first_subject}), {word} for {beyond_s:.2f} s")
    return Violation(
        invariant, detail, subject=worst_subject, worst_value=crossing.worst_value,
        limit=limit, excess=abs(limit - crossing.worst_value), worst_time_s=worst_t,
        first_time_s=first_t, first_subject=first_subject, time_beyond_s=beyond_s)


_TELEMETRY_FIELDS = ("command", "estimate", "λ̄")


def _check_finite(record: RunRecord) -> list[Violation]:
    """Present samples must be finite; ±inf is never a missing sample. Says how many, and
    which drone's which field first, when."""
    present = ~telemetry_missing(record)
    telemetry = (record.velocities_m_s, record.estimates, record.lambda_bar)
    bad = [np.any(~np.isfinite(a), axis=tuple(range(2, a.ndim))) & present for a in telemetry]
    counts = [int(b.sum()) for b in bad]
    infinite_drones = np.isinf(record.drone_positions_m).any(axis=2)  # (K, N)
    infinite_targets = np.isinf(record.target_positions_m).any(axis=2)  # (K, M)
    infinite = bool(infinite_drones.any() or infinite_targets.any())
    if sum(counts) == 0 and not infinite:
        return []
    firsts: list[tuple[float, str]] = []
    for name, b in zip(_TELEMETRY_FIELDS, bad, strict=True):
        if b.any():
            k, i = np.argwhere(b)[0]
            firsts.append((float(record.times_s[k]), f"drone {i}'s {name}"))
    for name, b in (("drone", infinite_drones), ("target", infinite_targets)):
        if b.any():
            k, i = np.argwhere(b)[0]
            firsts.append((float(record.times_s[k]), f"{name} {i}'s position (inf)"))
    first_t, first_subject = min(firsts)
    return [Violation(
        "finite", f"a position, command, estimate or λ̄ is NaN/inf ({sum(counts)} received "
                  f"samples non-finite{', a position is inf' if infinite else ''}); first: "
                  f"{first_subject} at t = {first_t:.2f} s",
        subject=first_subject, first_time_s=first_t, first_subject=first_subject)]


def _check_lambda_bar(record: RunRecord) -> list[Violation]:
    cfg = record.config
    eps, tol = cfg.gramian.epsilon, cfg.checks.lambda_tolerance
    floor = eps - tol
    k0 = start_index(record)
    violations = []
    for r in range(record.target_positions_m.shape[1]):
        lam = record.lambda_bar[k0:, :, r]
        if not np.isfinite(lam).any():
            violations.append(Violation(
                "lambda_bar", f"target {r}: not checked: no λ̄ sample after control.start_s = "
                              f"{cfg.control.start_s} s"))
            continue
        crossing = _crossing(lam, floor, below=True)
        if crossing is None:
            continue
        crossing = dataclasses.replace(crossing, worst_step=crossing.worst_step + k0,
                                       first_step=crossing.first_step + k0)
        violations.append(_violation(
            "lambda_bar", crossing, floor, record,
            _by_drone(f"target {r}"),
            f"target {r}: drone {crossing.worst_column} has λ̄ = {crossing.worst_value:.4f} "
            f"< ε − tol = {floor:.4f} (by {floor - crossing.worst_value:.4f})", "below"))
    return violations


def _check_collision(record: RunRecord) -> list[Violation]:
    cfg = record.config
    distance, pair = closest_pair_per_step(record.drone_positions_m)
    floor = cfg.control.collision_distance_m - cfg.checks.collision_tolerance_m
    if np.isnan(distance).all():
        return [Violation("collision", "not checked: no step with two drone positions")]
    crossing = _crossing(distance[:, None], floor, below=True)
    if crossing is None:
        return []

    def drones(k: int, _column: int) -> str:
        return f"drones {pair[k, 0]} and {pair[k, 1]}"

    worst = crossing.worst_value
    return [_violation(
        "collision", crossing, floor, record, drones,
        f"min pairwise distance {worst:.4f} m < Δ − tol = {floor:.4f} m (by "
        f"{floor - worst:.4f} m): {drones(crossing.worst_step, 0)}", "below")]


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
    tolerance = record.config.checks.envelope_tolerance_m
    out = []
    for kind, margins in envelope_margin_series(record).items():
        if np.isnan(margins).all():
            out.append(Violation("envelope", f"{kind}: not checked: no drone position"))
            continue
        crossing = _crossing(margins, -tolerance, below=True)
        if crossing is None:
            continue
        out.append(_violation(
            "envelope", crossing, -tolerance, record,
            _by_drone(kind),
            f"drone {crossing.worst_column} went {-crossing.worst_value:.4f} m beyond the "
            f"{kind} (tolerance {tolerance} m)", "beyond"))
    return out


_AXES = "xyz"


def _check_velocity_bound(record: RunRecord) -> list[Violation]:
    u_max = record.config.control.u_max_m_s
    speeds = np.abs(record.velocities_m_s)  # (K, N, 3)
    if np.isnan(speeds).all():
        return [Violation("velocity_bound", "not checked: no command in the record")]
    k, n = speeds.shape[:2]
    limit = u_max + 1e-9
    crossing = _crossing(speeds.reshape(k, n * 3), limit, below=False)
    if crossing is None:
        return []

    def axis(_k: int, column: int) -> str:
        return f"drone {column // 3}, u_{_AXES[column % 3]}"

    return [_violation(
        "velocity_bound", crossing, u_max, record, axis,
        f"a command reaches |u_k| = {crossing.worst_value:.4f} m/s > u_max = {u_max} m/s "
        f"({axis(0, crossing.worst_column)})", "above")]


def check_invariants(record: RunRecord) -> list[Violation]:
    """SPEC invariants with the scenario's tolerances ([checks] of the config).

    Checked on the samples present; an invariant with nothing to check is a violation.
    """
    return [*_check_finite(record), *_check_lambda_bar(record), *_check_collision(record),
            *_check_envelope(record), *_check_velocity_bound(record), *check_network(record)]
