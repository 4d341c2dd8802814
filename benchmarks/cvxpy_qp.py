"""The local QP of a drone (thesis 3.36, relaxed) written in CVXPY, for the comparisons.

Inputs are those of ``LocalQpWorkspace.solve``: u_d, the velocity part of the rows
(column-major: x coefficients of every row, then y, then z; rows: M localization, M
weight-sum, N − 1 collision slots), their lower bounds and the weights w_r. The problem:

    min ‖u − u_d‖² + Σ_r K_δ max(w_r, w_floor) (δ_r² + δw_r²)
    s.t. L_gψ1,r u + δ_r ≥ b_r,  ∂w_r/∂p u + δw_r ≥ c_r,  2(p − p_j)ᵀu ≥ −α h_j/2 (drones in
         range),  −u_max ≤ u ≤ u_max,  δ ≥ 0,  δw ≥ 0,

the same minimizer as the solver form ½zᵀPz + qᵀz (it differs by the constant ‖u_d‖²).

- ``solve_rebuilt``: everything built from scratch at every call (``cp.Variable``, the
  constraints, ``cp.Problem(...).solve()``), as the thesis' simulations did.
- ``ParametrizedQp``: built once with ``cp.Parameter``s (DPP), re-solved with new values.
- ``CvxpyRebuiltWorkspace``: a drop-in for ``LocalQpWorkspace`` that solves by
  ``solve_rebuilt``, to time a whole agent step with the thesis' QP path.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import cvxpy as cp
import numpy as np
from numpy.typing import NDArray

from swarm.core.qp import INACTIVE_ROW_LOWER, QpSolution

Array = NDArray[np.float64]

# Tight settings for each solver (PIQP as the agents ran it before DAQP replaced it: eps_abs
# 1e-9, eps_rel 1e-10, 200 iterations, dense backend).
SOLVER_OPTIONS: dict[str, dict[str, object]] = {
    "PIQP": {"backend": "dense", "eps_abs": 1e-9, "eps_rel": 1e-10, "max_iter": 200},
    "CLARABEL": {"tol_gap_abs": 1e-9, "tol_gap_rel": 1e-10, "tol_feas": 1e-9},
    "OSQP": {"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iter": 20_000, "polishing": True},
}


@dataclass(frozen=True)
class QpData:
    """One local QP as ``LocalQpWorkspace.solve`` receives it, plus the constants."""

    m_targets: int
    n_collision: int
    nominal: tuple[float, float, float]
    u_columns: tuple[float, ...]
    lower: tuple[float, ...]
    weights: tuple[float, ...]
    slack_weight: float
    weight_floor: float
    u_max: float

    @property
    def u_rows(self) -> Array:
        """(rows, 3): the velocity coefficients of every row."""
        n_rows = len(self.lower)
        return np.asarray(self.u_columns, dtype=float).reshape(3, n_rows).T

    def padded(self, n_collision: int) -> QpData:
        """The same QP with always-true placeholder rows ``0 ≥ −1`` up to ``n_collision``
        collision rows (an agent passes only the drones within R_ca; a parametrized problem
        has one fixed shape)."""
        extra = n_collision - self.n_collision
        if extra < 0:
            raise ValueError(f"{self.n_collision} collision rows do not fit in {n_collision}")
        n_rows = len(self.lower)
        columns = np.asarray(self.u_columns, dtype=float).reshape(3, n_rows)
        columns = np.hstack((columns, np.zeros((3, extra))))
        return dataclasses.replace(
            self, n_collision=n_collision, u_columns=tuple(columns.ravel().tolist()),
            lower=(*self.lower, *([INACTIVE_ROW_LOWER] * extra)))

    @property
    def penalties(self) -> Array:
        """K_δ max(w_r, w_floor) of each target's two slacks."""
        return self.slack_weight * np.maximum(np.asarray(self.weights), self.weight_floor)


def solve_rebuilt(qp: QpData, solver: str) -> Array:
    """Build the QP in CVXPY from nothing and solve it; returns z = [u, δ, δw]."""
    m = qp.m_targets
    rows, lower = qp.u_rows, np.asarray(qp.lower)
    u = cp.Variable(3)
    delta = cp.Variable(m)
    delta_w = cp.Variable(m)
    penalty = qp.penalties
    cost = (cp.sum_squares(u - np.asarray(qp.nominal))
            + penalty @ cp.square(delta) + penalty @ cp.square(delta_w))
    constraints = [rows[:m] @ u + delta >= lower[:m],
                   rows[m:2 * m] @ u + delta_w >= lower[m:2 * m],
                   u >= -qp.u_max, u <= qp.u_max, delta >= 0, delta_w >= 0]
    collision = [k for k in range(2 * m, len(qp.lower))
                 if qp.lower[k] != INACTIVE_ROW_LOWER or np.any(rows[k])]
    if collision:
        constraints.append(rows[collision] @ u >= lower[collision])
    problem = cp.Problem(cp.Minimize(cost), constraints)
    problem.solve(solver=solver, **SOLVER_OPTIONS.get(solver, {}))
    if u.value is None:
        raise cp.SolverError(f"{solver}: {problem.status}")
    return np.concatenate((u.value, delta.value, delta_w.value))


class ParametrizedQp:
    """The QP built once with parameters for u_d, rows, bounds and penalties (DPP)."""

    def __init__(self, m_targets: int, n_collision: int, u_max: float, solver: str) -> None:
        n_rows = 2 * m_targets + n_collision
        self.solver = solver
        self.nominal = cp.Parameter(3)
        self.rows = cp.Parameter((n_rows, 3))
        self.lower = cp.Parameter(n_rows)
        self.root_penalty = cp.Parameter(m_targets, nonneg=True)  # √(K_δ max(w, w_floor))
        self.u = cp.Variable(3)
        self.delta = cp.Variable(m_targets)
        self.delta_w = cp.Variable(m_targets)
        cost = (cp.sum_squares(self.u - self.nominal)
                + cp.sum_squares(cp.multiply(self.root_penalty, self.delta))
                + cp.sum_squares(cp.multiply(self.root_penalty, self.delta_w)))
        slacks = cp.hstack([self.delta, self.delta_w, np.zeros(n_collision)])
        constraints = [self.rows @ self.u + slacks >= self.lower, self.u >= -u_max,
                       self.u <= u_max, self.delta >= 0, self.delta_w >= 0]
        self.problem = cp.Problem(cp.Minimize(cost), constraints)
        if not self.problem.is_dpp():
            raise RuntimeError("the parametrized QP is not DPP")

    def solve(self, qp: QpData) -> Array:
        qp = qp.padded(self.rows.shape[0] - 2 * qp.m_targets)
        self.nominal.value = np.asarray(qp.nominal)
        self.rows.value = qp.u_rows
        self.lower.value = np.asarray(qp.lower)
        self.root_penalty.value = np.sqrt(qp.penalties)
        self.problem.solve(solver=self.solver, **SOLVER_OPTIONS.get(self.solver, {}))
        if self.u.value is None:
            raise cp.SolverError(f"{self.solver}: {self.problem.status}")
        return np.concatenate((self.u.value, self.delta.value, self.delta_w.value))


class CvxpyRebuiltWorkspace:
    """``LocalQpWorkspace.solve`` by ``solve_rebuilt`` (the thesis' QP path, relaxed QP)."""

    def __init__(self, m_targets: int, n_collision: int, *, slack_weight: float,
                 weight_floor: float, u_max: float, solver: str = "PIQP") -> None:
        self.m_targets, self.n_collision, self.solver = m_targets, n_collision, solver
        self.slack_weight, self.weight_floor, self.u_max = slack_weight, weight_floor, u_max

    def solve(self, nominal: tuple[float, float, float], u_columns: list[float],
              lower: list[float], weights: list[float],
              u_box: tuple[list[float], list[float]] | None = None) -> QpSolution:
        if u_box is not None:  # the thesis' QP has the fixed box |u_k| ≤ u_max only
            raise ValueError("CvxpyRebuiltWorkspace: no rate box (command_accel_limit_m_s2 "
                             "must be 0 for the CVXPY comparison)")
        qp = QpData(self.m_targets, len(lower) - 2 * self.m_targets, tuple(nominal),
                    tuple(u_columns),
                    tuple(lower), tuple(weights), self.slack_weight, self.weight_floor,
                    self.u_max)
        start = time.perf_counter()
        try:
            z = solve_rebuilt(qp, self.solver)
            found, status = True, "solved"
        except cp.SolverError as err:
            z, found, status = np.zeros(3 + 2 * self.m_targets), False, str(err)
        return QpSolution(found=found, z=z, status=status, iterations=0,
                          solve_time_s=time.perf_counter() - start, max_violation=0.0)
