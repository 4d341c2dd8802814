"""QPs for tests: one the solver cannot solve, as an agent would keep it."""

from __future__ import annotations

import numpy as np

from swarm.core.qp import FailedQp, QpSolver, build_local_qp


def infeasible_hard_qp(drone_id: int = 2, step: int = 41) -> FailedQp:
    """Rows u_x ≥ 1 and −u_x ≥ 1: no u meets both; as the solver answers it."""
    qp = build_local_qp(np.zeros(3), np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]),
                        np.array([1.0, 1.0]), np.zeros((2, 3)), np.full(2, -1.0),
                        np.zeros((1, 3)), np.full(1, -1.0), np.ones(2), relaxed=False,
                        slack_weight=1e6, weight_floor=1e-3, u_max=3.0)
    solution = QpSolver().solve(qp)
    assert not solution.found
    return FailedQp(drone_id, step, "hard", qp, solution.status, solution.iterations,
                    solution.max_violation)
