"""The local QP of each drone, built as plain matrices and solved with PIQP (SPEC §9).

Decision vector ``z = [u (3), δ_1..δ_M, δw_1..δw_M]`` (relaxed, 3.36) or ``z = u`` (hard, 3.37).
Cost ``‖u − u_d‖² + Σ_r K_δ max(w_r, w_floor)(δ_r² + δw_r²)``, written for PIQP as
``½ zᵀPz + qᵀz``. Rows ``a·z ≥ lower``. The number of rows is fixed per drone (M localization,
M weight-sum and N − 1 collision rows) so one PIQP solver is set up once and updated each
step; a collision row for a drone out of range is the always-true ``0 ≥ −1``.

PIQP (an interior-point method) is run to a duality gap of 1e-14; where a slack's force makes
its answer inexact, ``polish_active_set`` solves the KKT system of the active constraints.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import piqp
from numpy.typing import NDArray

from swarm.core.records import record

Array = NDArray[np.float64]

INACTIVE_ROW_LOWER = -1.0  # "0·z ≥ −1": an always-satisfied placeholder row
NOMINAL_FEASIBLE = "NOMINAL_FEASIBLE"  # status when u_d itself is the optimum (no solve)


@dataclass(frozen=True)
class LocalQp:
    """One instance of the local QP, independent of any solver (SPEC §9)."""

    cost_hessian: NDArray[np.float64]  # P (n×n)
    cost_linear: NDArray[np.float64]  # q (n)
    rows: NDArray[np.float64]  # A (m×n), constraints A z ≥ lower
    lower: NDArray[np.float64]  # (m)
    z_min: NDArray[np.float64]  # (n)
    z_max: NDArray[np.float64]  # (n)

    @property
    def n_variables(self) -> int:
        return self.cost_linear.shape[0]

    def objective(self, z: NDArray[np.float64]) -> float:
        return float(0.5 * z @ self.cost_hessian @ z + self.cost_linear @ z)

    def max_violation(self, z: NDArray[np.float64]) -> float:
        """Largest violation of any row or bound at z (0 when z is feasible)."""
        row_gap = np.max(self.lower - self.rows @ z, initial=0.0)
        box_gap = max(np.max(self.z_min - z), np.max(z - self.z_max), 0.0)
        return float(max(row_gap, box_gap))


def build_local_qp(
    nominal_velocity: NDArray[np.float64],
    localization_rows: NDArray[np.float64],
    localization_lower: NDArray[np.float64],
    weight_rows: NDArray[np.float64],
    weight_lower: NDArray[np.float64],
    collision_rows: NDArray[np.float64],
    collision_lower: NDArray[np.float64],
    weights: NDArray[np.float64],
    *,
    relaxed: bool,
    slack_weight: float,
    weight_floor: float,
    u_max: float,
) -> LocalQp:
    """Assemble P, q, A, lower and the box of the local QP (SPEC §9, thesis 3.36 / 3.37).

    Args:
        nominal_velocity: u_d (3).
        localization_rows, localization_lower: L_gi ψ1 (M×3) and −(c + ψ1)/N − d_i (M).
        weight_rows, weight_lower: ∂w/∂p_i (M×3) and the weight-sum bound (M).
        collision_rows, collision_lower: 2(p_i − p_j)ᵀ and −α h/2, inactive rows all zero.
        weights: w_ir (M), scaling the slack penalties.
        relaxed: slack columns (3.36) or none (3.37).
    """
    m_targets = localization_rows.shape[0]
    n_slack = 2 * m_targets if relaxed else 0
    n = 3 + n_slack
    hessian = np.zeros((n, n))
    hessian[0, 0] = hessian[1, 1] = hessian[2, 2] = 2.0
    linear = np.zeros(n)
    linear[:3] = -2.0 * nominal_velocity
    z_min = np.full(n, -u_max)
    z_max = np.full(n, u_max)
    u_rows = np.vstack((localization_rows, weight_rows, collision_rows))
    rows = np.zeros((u_rows.shape[0], n))
    rows[:, :3] = u_rows
    if relaxed:
        penalty = 2.0 * slack_weight * np.maximum(weights, weight_floor)
        slack_diag = np.concatenate((penalty, penalty))
        hessian[3:, 3:] = np.diag(slack_diag)
        z_min[3:] = 0.0
        z_max[3:] = np.inf
        # δ_r enters localization row r, δw_r enters weight row r.
        rows[np.arange(2 * m_targets), 3 + np.arange(2 * m_targets)] = 1.0
    lower = np.concatenate((localization_lower, weight_lower, collision_lower))
    return LocalQp(hessian, linear, rows, lower, z_min, z_max)


@dataclass(frozen=True)
class QpSolution:
    """Result of one local QP solve; ``found`` is False on any solver failure."""

    found: bool
    z: NDArray[np.float64]
    status: str
    iterations: int
    solve_time_s: float
    max_violation: float

    @property
    def velocity(self) -> NDArray[np.float64]:
        return self.z[:3]


@dataclass(frozen=True)
class FailedQp:
    """A local QP that got no acceptable solution, as PIQP was given it, with PIQP's answer:
    what it takes to solve it again outside the swarm (``QpSolver().solve(failed.qp)``).

    ``attempt`` names which QP of the step it was (``DroneAgent``'s fallback order, SPEC §9):
    "hard" (3.37), "relaxed" (3.36) or "relaxed, full box" (3.36 without the rate box)."""

    drone_id: int
    step: int
    attempt: str
    qp: LocalQp
    status: str
    iterations: int
    max_violation: float

    def describe(self) -> str:
        """One line for a log, e.g. ``drone 2: step 41: hard QP not solved: PIQP_PRIMAL_INFEASIBLE
        after 23 iterations (max violation inf; 3 variables, 11 rows)``."""
        rows, n = self.qp.rows.shape
        return (f"drone {self.drone_id}: step {self.step}: {self.attempt} QP not solved: "
                f"{self.status} after {self.iterations} iterations (max violation "
                f"{self.max_violation:.3g}; {n} variables, {rows} rows)")


# Polishing (``polish_active_set``): a constraint whose residual at PIQP's point is at most
# ACTIVE_RESIDUAL (relative to 1 + |bound|) is taken as active; the polished point must meet
# every other constraint to POLISH_FEASIBILITY (same scale), and each multiplier λ_i must be
# ≥ −POLISH_DUAL · F / ‖g_i‖, F the largest force |λ_k|·‖g_k‖ of the system (+1): the
# multipliers of active slack rows reach ~1e8 (2 K_δ w δ), and round-off in the others
# scales with them, not with their own size.
ACTIVE_RESIDUAL = 1e-6
POLISH_FEASIBILITY = 1e-10
POLISH_DUAL = 1e-12
POLISH_MAX_CHANGES = 6
# PIQP's answer is polished when some slack pushes with a force 2 K_δ max(w, w_floor) δ_r above
# this: measured on 450 relaxed QPs of three families (rows of gain 1e-3 to 5, slacks 0.01 to
# 500), PIQP alone (duality gap 1e-14) was within 1.1e-9 m/s of the optimum below 1e7 and
# up to 4.5e-3 m/s off between 1e7 and 1e8; Case 2's largest is ~5e3.
POLISH_FORCE = 1e6


def slack_force(hessian_diagonal: Array | list[float], z: Array | list[float]) -> float:
    """The largest force P_rr·δ_r of a slack at z (z = [u, δ...]; 0 for the hard QP)."""
    return max((p * d for p, d in zip(hessian_diagonal[3:], z[3:], strict=True)), default=0.0)


def polish_active_set(hessian: Array, linear: Array, rows: Array, lower: Array,
                      z_min: Array, z_max: Array, z: Array) -> Array | None:
    """The exact optimum of a strictly convex QP near an approximate one (SPEC §9).

    ``min ½zᵀPz + qᵀz  s.t.  rows·z ≥ lower,  z_min ≤ z ≤ z_max``. PIQP, an interior-point
    method, stops at residuals of ~1e-9 relative to the problem's scale; when active slacks
    of weight K_δ w ~ 1e6 make the objective ~1e9, that leaves u up to ~1e-3 m/s from the
    optimum (measured). The optimum is the solution of the KKT system of its active
    constraints W:

        [ P   −G_Wᵀ ] [ z ]   [ −q  ]
        [ G_W   0   ] [ λ ] = [ h_W ],   with G z ≥ h every row and bound, and λ ≥ 0,

    so W is guessed from z (residual ≤ ``ACTIVE_RESIDUAL``), the system solved, and the
    guess mended a few times as a primal-dual active-set method does (add the most violated
    constraint, drop the most negative multiplier, by force). Returns the polished z, or None
    if no active set within ``POLISH_MAX_CHANGES`` changes gives a point that meets every
    constraint to ``POLISH_FEASIBILITY`` with multipliers that are not negative beyond
    round-off (``POLISH_DUAL``): the caller keeps PIQP's z.
    """
    n = z.shape[0]
    low_finite = np.isfinite(z_min)
    high_finite = np.isfinite(z_max)
    eye = np.eye(n)
    constraints = np.vstack((rows, eye[low_finite], -eye[high_finite]))
    bounds = np.concatenate((lower, z_min[low_finite], -z_max[high_finite]))
    # The variable each constraint bounds (−1: a row), and where an active bound puts it.
    bounded = np.concatenate((np.full(rows.shape[0], -1), np.flatnonzero(low_finite),
                              np.flatnonzero(high_finite)))
    at_bound = np.concatenate((np.zeros(rows.shape[0]), z_min[low_finite], z_max[high_finite]))
    scale = 1.0 + np.abs(bounds)
    norms = np.sqrt(np.einsum("ij,ij->i", constraints, constraints))
    active = np.flatnonzero((constraints @ z - bounds <= ACTIVE_RESIDUAL * scale)
                            & (norms > 0.0))
    rhs_top = -linear
    for _ in range(POLISH_MAX_CHANGES + 1):
        k = active.shape[0]
        if k > n:
            return None
        g_active = constraints[active]
        kkt = np.zeros((n + k, n + k))
        kkt[:n, :n] = hessian
        kkt[:n, n:] = -g_active.T
        kkt[n:, :n] = g_active
        try:
            solution = np.linalg.solve(kkt, np.concatenate((rhs_top, bounds[active])))
        except np.linalg.LinAlgError:  # dependent active rows
            return None
        z_new, multipliers = solution[:n], solution[n:]
        if not np.all(np.isfinite(solution)):
            return None
        # A variable at an active bound is the bound: the solve leaves it off by round-off
        # of the system's largest forces (1e-9 when slacks are large).
        on_bound = active[bounded[active] >= 0]
        z_new[bounded[on_bound]] = at_bound[on_bound]
        residual = (constraints @ z_new - bounds) / scale
        residual[active] = 0.0  # met by the solve, up to its round-off
        worst = int(np.argmin(residual))
        if residual[worst] < -POLISH_FEASIBILITY:
            active = np.append(active, worst)
            continue
        if k:
            forces = multipliers * norms[active]
            if forces.min() < -POLISH_DUAL * (1.0 + float(np.abs(forces).max())):
                active = np.delete(active, int(np.argmin(forces)))
                continue
        return z_new
    return None


def _new_piqp_solver() -> piqp.DenseSolver:
    solver = piqp.DenseSolver()
    settings = solver.settings
    settings.verbose = False
    settings.eps_abs = 1e-9
    settings.eps_rel = 1e-10
    # The duality gap (default 1e-9 relative to the objective, ~1e7 with slacks in use) to
    # 1e-14: PIQP's u was up to 4e-5 m/s off the optimum at slacks ≈ 12.5, 1e-9 with this
    # (about 5 more iterations). Larger forces: polish_active_set.
    settings.eps_duality_gap_rel = 1e-14
    settings.eps_duality_gap_abs = 1e-14
    settings.max_iter = 200
    return solver


_STATUS_NAMES: dict[object, str] = {}


def _status_name(status: object) -> str:
    name = _STATUS_NAMES.get(status)
    if name is None:
        name = _STATUS_NAMES[status] = str(status).rsplit(".", 1)[-1]
    return name


@dataclass
class QpSolver:
    """One PIQP dense solver per drone and QP shape, set up once and updated each step."""

    feasibility_tolerance: float = 1e-6
    _solver: piqp.DenseSolver | None = field(default=None, init=False, repr=False)
    _shape: tuple[int, int] | None = field(default=None, init=False, repr=False)

    def solve(self, qp: LocalQp) -> QpSolution:
        hessian = np.asfortranarray(qp.cost_hessian)
        rows = np.asfortranarray(qp.rows)
        upper = np.full(qp.lower.shape, np.inf)
        start = time.perf_counter()
        shape = qp.rows.shape
        if self._solver is None or self._shape != shape:
            self._solver = _new_piqp_solver()
            self._solver.setup(hessian, qp.cost_linear, None, None, rows, qp.lower, upper,
                               qp.z_min, qp.z_max)
            self._shape = shape
        else:
            self._solver.update(P=hessian, c=qp.cost_linear, G=rows, h_l=qp.lower, h_u=upper,
                                x_l=qp.z_min, x_u=qp.z_max)
        status = self._solver.solve()
        result = self._solver.result
        z = np.array(result.x, dtype=float)
        solved = status == piqp.PIQP_SOLVED and bool(np.all(np.isfinite(z)))
        if solved and slack_force(np.diag(qp.cost_hessian), z) > POLISH_FORCE:
            polished = polish_active_set(qp.cost_hessian, qp.cost_linear, qp.rows, qp.lower,
                                         qp.z_min, qp.z_max, z)
            z = z if polished is None else polished
        elapsed = time.perf_counter() - start
        violation = qp.max_violation(z) if solved else float("inf")
        return QpSolution(
            found=solved and violation <= self.feasibility_tolerance,
            z=z,
            status=_status_name(status),
            iterations=int(result.info.iter),
            solve_time_s=elapsed,
            max_violation=violation,
        )


def rate_limited_box(previous: tuple[float, float, float], max_change: float,
                     u_max: float) -> tuple[list[float], list[float]]:
    """Bounds of u this step: |u_k − u_prev,k| ≤ a_max·ΔT (``max_change``) and |u_k| ≤ u_max.

    ``previous`` is the command of the last step (inside [−u_max, u_max]), so the box is never
    empty. As bounds of the QP's variables they are constraints like the barrier rows: a
    solution meets both, and a QP that cannot is infeasible (the caller's fallback), never a
    command that jumps.
    """
    low = [max(-u_max, u - max_change) for u in previous]
    high = [min(u_max, u + max_change) for u in previous]
    return low, high


class LocalQpWorkspace:
    """The local QP of one drone in preallocated matrices, with its own PIQP solver.

    ``solve(...)`` is ``QpSolver().solve(build_local_qp(...))`` for a drone whose QP shape
    (M targets, ``n_collision`` collision slots, relaxed or hard) never changes: the same
    matrices, the same solver settings, set up on the first solve and updated afterwards, so
    the same solution up to round-off. Only the entries that change are written: the velocity
    columns of the rows, the bounds, u_d, the slack penalties and the box of u (a rate box,
    ``rate_limited_box``, moves every solve); PIQP receives P, c and the box only when they
    changed (the infinite upper bounds are fixed at setup), which moves its re-scaled data by
    round-off (seen: 1e-20 in z).
    """

    def __init__(self, m_targets: int, n_collision: int, *, relaxed: bool, slack_weight: float,
                 weight_floor: float, u_max: float, feasibility_tolerance: float = 1e-6) -> None:
        n_slack = 2 * m_targets if relaxed else 0
        n = 3 + n_slack
        n_rows = 2 * m_targets + n_collision
        self.m_targets, self.relaxed, self.u_max = m_targets, relaxed, float(u_max)
        self.slack_weight, self.weight_floor = slack_weight, weight_floor
        self.feasibility_tolerance = feasibility_tolerance
        self.hessian = np.zeros((n, n), order="F")
        self.hessian[0, 0] = self.hessian[1, 1] = self.hessian[2, 2] = 2.0
        self.linear = np.zeros(n)
        self.rows = np.zeros((n_rows, n), order="F")
        self.lower = np.zeros(n_rows)
        self.upper = np.full(n_rows, np.inf)
        self.z_min = np.full(n, -u_max)
        self.z_max = np.full(n, u_max)
        if relaxed:
            self.z_min[3:] = 0.0
            self.z_max[3:] = np.inf
            self.rows[np.arange(n_slack), 3 + np.arange(n_slack)] = 1.0
        # Writable views: the u columns of the rows (contiguous in Fortran order) and the
        # slack part of P's diagonal.
        self._u_block = self.rows.T.reshape(-1)[:3 * n_rows]
        self._slack_diagonal = self.hessian.T.reshape(-1)[3 * (n + 1)::n + 1]
        self._penalties: list[float] | None = None
        self._nominal: tuple[float, float, float] | None = None
        self._solver: piqp.DenseSolver | None = None
        self._u_low = [-self.u_max] * 3  # the box of u of the current solve
        self._u_high = [self.u_max] * 3

    def solve(self, nominal: tuple[float, float, float], u_columns: list[float],
              lower: list[float], weights: list[float],
              u_box: tuple[list[float], list[float]] | None = None) -> QpSolution:
        """Solve with u_d, the velocity part of the rows (column-major: the x coefficients of
        every row, then y, then z; rows in the order localization, weight-sum, collision),
        their lower bounds and the weights w_r; ``u_box`` = (low, high) bounds of u for this
        solve (``rate_limited_box``), None: the fixed box |u_k| ≤ u_max.

        When u_d itself meets every row with zero slacks and lies in the box, it is the
        optimum: the cost is a sum of squares that is zero there and positive elsewhere (P is
        positive definite), so PIQP is not called (status ``NOMINAL_FEASIBLE``, 0 iterations).
        Only exact feasibility counts (no tolerance), so the answer is the QP's own optimum,
        not an approximation of it. Checked before any matrix is touched: the solver's data
        stay as they were at its last update.
        """
        start = time.perf_counter()
        u_max = self.u_max
        u_low, u_high = u_box if u_box is not None else ([-u_max] * 3, [u_max] * 3)
        self._u_low, self._u_high = u_low, u_high
        if self._max_violation(list(nominal), u_columns, lower) == 0.0:
            z = np.zeros(self.linear.shape[0])
            z[:3] = nominal
            return record(QpSolution, dict(
                found=True, z=z, status=NOMINAL_FEASIBLE, iterations=0,
                solve_time_s=time.perf_counter() - start, max_violation=0.0))
        self._u_block[:] = u_columns
        self.lower[:] = lower
        hessian_changed = linear_changed = False
        if self.relaxed:
            k, floor = self.slack_weight, self.weight_floor
            penalties = [2.0 * k * max(w, floor) for w in weights]
            if penalties != self._penalties:
                self._slack_diagonal[:] = penalties + penalties
                self._penalties = penalties
                hessian_changed = True
        if nominal != self._nominal:
            self.linear[:3] = (-2.0 * nominal[0], -2.0 * nominal[1], -2.0 * nominal[2])
            self._nominal = nominal
            linear_changed = True
        box_changed = self.z_min[:3].tolist() != u_low or self.z_max[:3].tolist() != u_high
        if box_changed:
            self.z_min[:3], self.z_max[:3] = u_low, u_high
        if self._solver is None:
            self._solver = _new_piqp_solver()
            self._solver.setup(self.hessian, self.linear, None, None, self.rows, self.lower,
                               self.upper, self.z_min, self.z_max)
        else:
            self._solver.update(P=self.hessian if hessian_changed else None,
                                c=self.linear if linear_changed else None,
                                G=self.rows, h_l=self.lower,
                                x_l=self.z_min if box_changed else None,
                                x_u=self.z_max if box_changed else None)
        status = self._solver.solve()
        result = self._solver.result
        z = np.array(result.x, dtype=float)
        values = z.tolist()
        solved = status == piqp.PIQP_SOLVED and all(map(math.isfinite, values))
        if solved and self.relaxed and slack_force(
                [0.0, 0.0, 0.0, *self._penalties, *self._penalties], values) > POLISH_FORCE:
            polished = polish_active_set(self.hessian, self.linear, self.rows, self.lower,
                                         self.z_min, self.z_max, z)
            if polished is not None:
                z, values = polished, polished.tolist()
        elapsed = time.perf_counter() - start
        violation = self._max_violation(values, u_columns, lower) if solved else float("inf")
        return record(QpSolution, dict(
            found=solved and violation <= self.feasibility_tolerance, z=z,
            status=_status_name(status), iterations=int(result.info.iter),
            solve_time_s=elapsed, max_violation=violation))

    def current_qp(self) -> LocalQp:
        """The QP of the last solve that reached PIQP, as a solver-independent ``LocalQp`` of
        copies: ``build_local_qp`` of the same inputs, with the box of u that solve had. (A
        ``NOMINAL_FEASIBLE`` solve writes nothing, so it is not this QP.)"""
        return LocalQp(self.hessian.copy(), self.linear.copy(), self.rows.copy(),
                       self.lower.copy(), self.z_min.copy(), self.z_max.copy())

    def _max_violation(self, z: list[float], u_columns: list[float],
                       lower: list[float]) -> float:
        """``LocalQp.max_violation`` of the current QP at a finite z, on plain floats."""
        u0, u1, u2 = z[0], z[1], z[2]
        n_rows = len(lower)
        slacks = z[3:] + [0.0] * (n_rows - len(z) + 3)  # δ_r in row r (x + 0 = x elsewhere)
        worst = 0.0
        for bound, a0, a1, a2, slack in zip(lower, u_columns[:n_rows],
                                            u_columns[n_rows:2 * n_rows], u_columns[2 * n_rows:],
                                            slacks, strict=True):
            gap = bound - (a0 * u0 + a1 * u1 + a2 * u2 + slack)
            if not gap <= worst:  # larger, or NaN (which np.max propagates)
                if gap != gap:
                    return gap
                worst = gap
        for u, low, high in zip((u0, u1, u2), self._u_low, self._u_high, strict=True):
            worst = max(worst, low - u, u - high)
        for slack in z[3:]:
            worst = max(worst, 0.0 - slack)
        return float(worst)
