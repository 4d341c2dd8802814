"""The local QP of each drone, built as plain matrices and solved by DAQP or PIQP (SPEC §9).

Decision vector ``z = [u (3), δ_1..δ_M, δw_1..δw_M]`` (relaxed, 3.36) or ``z = u`` (hard, 3.37).
Cost ``‖u − u_d‖² + Σ_r K_δ max(w_r, w_floor)(δ_r² + δw_r²)``, written for the solver as
``½ zᵀPz + qᵀz``. Rows ``a·z ≥ lower``: M localization, M weight-sum and one collision row per
drone within R_ca, so the QP's size depends on the drones near this one, not on N; a solver
instance per number of rows is set up once and updated each step. (``0 ≥ −1``,
``INACTIVE_ROW_LOWER``, is an always-true row a caller may pad with.)

The solver is a backend behind ``QpBackend``, chosen by name (``[control] qp_solver``):
``"daqp"`` (``qp_daqp``, the default), a dual active-set method that ends on the optimum's
active set, so u is exact up to round-off however large the slacks of weight K_δ ~ 1e6; or
``"piqp"`` (``qp_piqp``, the design's solver), a proximal interior-point method whose u is
within a tolerance of the optimum (``tests/core/test_qp.py`` states both).
"""

from __future__ import annotations

import importlib
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from swarm.core.fast_dataclass import record
from swarm.core.kernels import qp_load as _qp_load
from swarm.core.kernels import qp_max_violation as _qp_max_violation

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
        n: int = self.cost_linear.shape[0]
        return n

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
    """A local QP that got no acceptable solution, as the solver was given it, with its answer:
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
        """One line for a log, e.g. ``drone 2: step 41: hard QP not solved: DAQP_INFEASIBLE
        after 23 iterations (max violation inf; 3 variables, 11 rows)``."""
        rows, n = self.qp.rows.shape
        return (f"drone {self.drone_id}: step {self.step}: {self.attempt} QP not solved: "
                f"{self.status} after {self.iterations} iterations (max violation "
                f"{self.max_violation:.3g}; {n} variables, {rows} rows)")


QP_SOLVERS = ("daqp", "piqp")  # [control] qp_solver: the backends, by name
DEFAULT_QP_SOLVER = "daqp"
_BACKEND_MODULES = {"daqp": ("swarm.core.qp_daqp", "DaqpBackend"),
                    "piqp": ("swarm.core.qp_piqp", "PiqpBackend")}


class QpBackend(Protocol):
    """What the local QP asks of a solver: one instance per QP shape, set up on its first
    solve and updated after, for ``min ½zᵀPz + qᵀz`` s.t. ``z_min ≤ z ≤ z_max`` and
    ``rows·z ≥ lower``, given in DAQP's bound form: ``bounds_lower`` = [z_min, lower] and
    ``bounds_upper`` = [z_max, +inf per row] (the first n bound z, the rest the rows). The
    arrays are C-contiguous and the caller does not change them between solves;
    ``hessian_changed`` False says P is the one of the last solve."""

    solved_status: str  # the status of an optimal solve, e.g. "DAQP_OPTIMAL"

    def solve(self, hessian: Array, linear: Array, rows: Array, bounds_lower: Array,
              bounds_upper: Array, *, hessian_changed: bool = True
              ) -> tuple[Array, bool, str, int]:
        """(z, optimal, status, iterations): ``optimal`` when the solver says z is its
        optimum (the caller checks that z is finite and feasible)."""
        ...


def backend_class(name: str) -> type[QpBackend]:
    """The backend named ``name`` (one of ``QP_SOLVERS``), its module imported on first use
    (an agent loads only the solver it runs); ValueError for any other name."""
    if name not in _BACKEND_MODULES:
        raise ValueError(f"qp_solver must be one of {', '.join(map(repr, QP_SOLVERS))} "
                         f"(got {name!r})")
    module, cls = _BACKEND_MODULES[name]
    backend: type[QpBackend] = getattr(importlib.import_module(module), cls)
    return backend


def solved_status(name: str) -> str:
    """The status of an optimal solve by the backend ``name`` ("DAQP_OPTIMAL", "PIQP_SOLVED")."""
    return backend_class(name).solved_status


@dataclass
class QpSolver:
    """Solves ``LocalQp``s with the backend ``solver`` (``QP_SOLVERS``): one instance per QP
    shape, set up once and updated."""

    feasibility_tolerance: float = 1e-6
    solver: str = DEFAULT_QP_SOLVER
    _model: QpBackend | None = field(default=None, init=False, repr=False)
    _shape: tuple[int, int] | None = field(default=None, init=False, repr=False)
    _backend: type[QpBackend] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._backend = backend_class(self.solver)

    def solve(self, qp: LocalQp) -> QpSolution:
        start = time.perf_counter()
        shape = qp.rows.shape
        if self._model is None or self._shape != shape:
            self._model, self._shape = self._backend(), shape
        z, optimal, status, iterations = self._model.solve(
            np.ascontiguousarray(qp.cost_hessian, dtype=float),
            np.ascontiguousarray(qp.cost_linear, dtype=float),
            np.ascontiguousarray(qp.rows, dtype=float),
            np.concatenate((qp.z_min, qp.lower)).astype(float),
            np.concatenate((qp.z_max, np.full(qp.lower.shape, np.inf))).astype(float))
        solved = optimal and bool(np.all(np.isfinite(z)))
        elapsed = time.perf_counter() - start
        violation = qp.max_violation(z) if solved else float("inf")
        return QpSolution(
            found=solved and violation <= self.feasibility_tolerance,
            z=z,
            status=status,
            iterations=iterations,
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


def estimate_free_rows(u_columns: list[float], lower: list[float], n_estimate_rows: int) -> None:
    """Blank the first ``n_estimate_rows`` rows (localization and weight-sum, which need the
    estimate) of the QP rows in place: each becomes ``0·z ≥ −1`` (``INACTIVE_ROW_LOWER``),
    always met, so its slack is 0 at the optimum; the rows after them (collision, envelope)
    stay as they are. ``u_columns`` is column-major (the x coefficients of every row, then y,
    then z), as ``LocalQpWorkspace.solve`` takes it. Before ``control.start_s`` the QP keeps
    only the safety rows this way (SPEC §9), with the same shape and workspace as after."""
    n_rows = len(lower)
    if not 0 <= n_estimate_rows <= n_rows or len(u_columns) != 3 * n_rows:
        raise ValueError(f"{n_estimate_rows} estimate rows of {n_rows} rows with "
                         f"{len(u_columns)} velocity coefficients (3 per row)")
    blank = [0.0] * n_estimate_rows
    for axis in range(3):
        u_columns[axis * n_rows:axis * n_rows + n_estimate_rows] = blank
    lower[:n_estimate_rows] = [INACTIVE_ROW_LOWER] * n_estimate_rows


@dataclass
class _RowBlock:
    """The rows and bounds of the local QP for one number of collision rows, with their solver
    instance: the bounds in the backends' form, [z_min, lower] and [z_max, +inf per row]."""

    rows: Array  # (2M + collisions, n), C order
    bounds_lower: Array  # (n + rows,)
    bounds_upper: Array  # (n + rows,)
    model: QpBackend
    hessian_version: int = -1  # the P its model was last given (``LocalQpWorkspace``)

    @property
    def lower(self) -> Array:
        """The rows' lower bounds (a view)."""
        return self.bounds_lower[self.rows.shape[1]:]


class LocalQpWorkspace:
    """The local QP of one drone in preallocated matrices, with its own solver instances.

    ``solve(...)`` is ``QpSolver(solver=...).solve(build_local_qp(...))`` for a drone whose M
    targets and kind (relaxed or hard) never change: the same matrices, the same settings,
    set up on the first solve and updated afterwards, so the same solution up to round-off.
    The collision rows are those of the drones within R_ca at this step, so their number
    changes: each number gets its own rows and solver instance the first time it comes up
    (``n_collision``: the one to prepare first), kept for when it comes back. Only the entries
    that change are written: the velocity columns of the rows, the bounds, u_d, the slack
    penalties and the box of u (a rate box, ``rate_limited_box``, moves every solve); the
    solver is given P only when the penalties changed since its workspace last saw them.
    """

    def __init__(self, m_targets: int, n_collision: int = 0, *, relaxed: bool,
                 slack_weight: float, weight_floor: float, u_max: float,
                 feasibility_tolerance: float = 1e-6, solver: str = DEFAULT_QP_SOLVER
                 ) -> None:
        n_slack = 2 * m_targets if relaxed else 0
        n = 3 + n_slack
        self.m_targets, self.relaxed, self.u_max = m_targets, relaxed, float(u_max)
        self.slack_weight, self.weight_floor = slack_weight, weight_floor
        self.feasibility_tolerance = feasibility_tolerance
        self.solver = solver
        self._backend = backend_class(solver)
        self.hessian = np.zeros((n, n))
        self.hessian[0, 0] = self.hessian[1, 1] = self.hessian[2, 2] = 2.0
        self.linear = np.zeros(n)
        # The bounds of z other than the box of u (rows' blocks copy them): δ ≥ 0.
        self._z_min = np.full(n, -u_max)
        self._z_max = np.full(n, u_max)
        if relaxed:
            self._z_min[3:] = 0.0
            self._z_max[3:] = np.inf
        self._hessian_version = 0
        self._blocks: dict[int, _RowBlock] = {}
        self._block = self._row_block(2 * m_targets + n_collision)
        self._u_low = [-self.u_max] * 3  # the box of u of the current solve
        self._u_high = [self.u_max] * 3

    @property
    def rows(self) -> Array:
        """The rows of the last solve that reached the solver (or of the first block
        prepared)."""
        return self._block.rows

    @property
    def lower(self) -> Array:
        return self._block.lower

    @property
    def z_min(self) -> Array:
        """The lower bounds of z of the last solve that reached the solver (a view)."""
        return self._block.bounds_lower[:self.linear.shape[0]]

    @property
    def z_max(self) -> Array:
        return self._block.bounds_upper[:self.linear.shape[0]]

    def _row_block(self, n_rows: int) -> _RowBlock:
        block = self._blocks.get(n_rows)
        if block is None:
            n = self.linear.shape[0]
            n_slack = n - 3
            if n_rows < 2 * self.m_targets:
                raise ValueError(f"the local QP has at least 2M = {2 * self.m_targets} rows, "
                                 f"got {n_rows}")
            rows = np.zeros((n_rows, n))
            if self.relaxed:
                rows[np.arange(n_slack), 3 + np.arange(n_slack)] = 1.0
            block = self._blocks[n_rows] = _RowBlock(
                rows, np.concatenate((self._z_min, np.zeros(n_rows))),
                np.concatenate((self._z_max, np.full(n_rows, np.inf))), self._backend())
        return block

    def solve(self, nominal: tuple[float, float, float], u_columns: list[float],
              lower: list[float], weights: list[float],
              u_box: tuple[list[float], list[float]] | None = None) -> QpSolution:
        """Solve with u_d, the velocity part of the rows (column-major: the x coefficients of
        every row, then y, then z; rows in the order localization, weight-sum, collision),
        their lower bounds and the weights w_r; ``u_box`` = (low, high) bounds of u for this
        solve (``rate_limited_box``), None: the fixed box |u_k| ≤ u_max.

        When u_d itself meets every row with zero slacks and lies in the box, it is the
        optimum: the cost is a sum of squares that is zero there and positive elsewhere (P is
        positive definite), so the solver is not called (status ``NOMINAL_FEASIBLE``, 0 iterations).
        Only exact feasibility counts (no tolerance), so the answer is the QP's own optimum,
        not an approximation of it. Checked before any matrix is touched: the matrices stay
        as they were at the last solve.
        """
        start = time.perf_counter()
        u_max = self.u_max
        u_low, u_high = u_box if u_box is not None else ([-u_max] * 3, [u_max] * 3)
        self._u_low, self._u_high = u_low, u_high
        if self._max_violation(nominal, u_columns, lower) == 0.0:  # also checks the lengths
            z = np.zeros(self.linear.shape[0])
            z[:3] = nominal
            return record(QpSolution, dict(
                found=True, z=z, status=NOMINAL_FEASIBLE, iterations=0,
                solve_time_s=time.perf_counter() - start, max_violation=0.0))
        block = self._block = self._row_block(len(lower))
        if _qp_load(u_columns, lower, nominal, u_low, u_high, weights, self.slack_weight,
                    self.weight_floor, block.rows, block.bounds_lower, block.bounds_upper,
                    self.linear, self.hessian):
            self._hessian_version += 1  # new slack penalties
        z, optimal, status, iterations = block.model.solve(
            self.hessian, self.linear, block.rows, block.bounds_lower, block.bounds_upper,
            hessian_changed=block.hessian_version != self._hessian_version)
        block.hessian_version = self._hessian_version
        values = z.tolist()
        solved = optimal and all(map(math.isfinite, values))
        elapsed = time.perf_counter() - start
        violation = self._max_violation(values, u_columns, lower) if solved else float("inf")
        return record(QpSolution, dict(
            found=solved and violation <= self.feasibility_tolerance, z=z,
            status=status, iterations=iterations,
            solve_time_s=elapsed, max_violation=violation))

    def current_qp(self) -> LocalQp:
        """The QP of the last solve that reached the solver, as a solver-independent ``LocalQp`` of
        copies: ``build_local_qp`` of the same inputs, with the box of u that solve had. (A
        ``NOMINAL_FEASIBLE`` solve writes nothing, so it is not this QP.)"""
        return LocalQp(self.hessian.copy(), self.linear.copy(), self.rows.copy(),
                       self.lower.copy(), self.z_min.copy(), self.z_max.copy())

    def _max_violation(self, z: Sequence[float], u_columns: list[float],
                       lower: list[float]) -> float:
        """``LocalQp.max_violation`` of the QP of these inputs at z, on plain floats (a NaN in
        z or the inputs is returned as the violation); reads no matrix. Compiled
        (``kernels.qp_max_violation``); raises ``ValueError`` unless ``u_columns`` holds 3
        floats per entry of ``lower``."""
        return _qp_max_violation(z, u_columns, lower, self._u_low, self._u_high)
