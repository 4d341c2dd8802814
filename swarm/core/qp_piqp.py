"""The local QP's PIQP backend (``[control] qp_solver = "piqp"``; SPEC §9).

PIQP is a proximal interior-point method: it stops when its primal and dual residuals and
its duality gap are small, absolutely or relative to the size of the problem's terms, so its
z is near the optimum rather than on it. With slacks of weight K_δ ~ 1e6 far from zero the
objective reaches ~1e9, and PIQP's default stop on the gap (1e-8 absolute, 1e-9 relative)
left u up to 1.5e-5 m/s off the optimum; with the gap at 1e-14 (below) u was within 3.3e-9
m/s of a brute-force optimum on every family of ``tests/core/test_qp.py``, as DAQP's.

The interface is the one of ``swarm.core.qp.QpBackend``: ``rows·z ≥ lower`` becomes
PIQP's ``h_l ≤ G z ≤ h_u`` with G = rows, h_l = lower, h_u = +inf, and the box its x_l, x_u.
"""

from __future__ import annotations

import numpy as np
import piqp
from numpy.typing import NDArray

Array = NDArray[np.float64]

SOLVED = "PIQP_SOLVED"
# Residuals to 1e-9 absolute, 1e-10 relative (PIQP's defaults: 1e-8, 1e-9). The duality
# gap decides how close u gets (module docstring): 1e-14, absolute and relative, costs about
# 5 iterations more than PIQP's default stop (median 19 on Case 2's QPs and on the test
# families, at most 51). The iteration limit ends a QP that does not converge (a P that is
# not positive definite) in about 1 ms.
EPS_ABS = 1e-9
EPS_REL = 1e-10
EPS_DUALITY_GAP_ABS = 1e-14
EPS_DUALITY_GAP_REL = 1e-14
ITERATION_LIMIT = 200


def new_solver() -> piqp.DenseSolver:
    """A dense PIQP solver with this backend's settings."""
    solver = piqp.DenseSolver()
    settings = solver.settings
    settings.verbose = False
    settings.eps_abs = EPS_ABS
    settings.eps_rel = EPS_REL
    settings.check_duality_gap = True
    settings.eps_duality_gap_abs = EPS_DUALITY_GAP_ABS
    settings.eps_duality_gap_rel = EPS_DUALITY_GAP_REL
    settings.max_iter = ITERATION_LIMIT
    return solver


class PiqpBackend:
    """One dense PIQP solver for QPs of one shape: ``min ½zᵀPz + qᵀz`` s.t. ``z_min ≤ z ≤
    z_max`` and ``rows·z ≥ lower``, given in DAQP's bound form (``bounds_lower`` = [z_min,
    lower], ``bounds_upper`` = [z_max, +inf per row]). Set up on the first solve, updated
    after (PIQP copies what it is given; an interior-point method starts each solve afresh).
    PIQP takes column-major matrices: the rows are copied to that order at each solve, P is
    passed as its transpose (the same matrix: P is symmetric)."""

    solved_status = SOLVED

    def __init__(self) -> None:
        self._solver: piqp.DenseSolver | None = None
        self._n = 0

    def solve(self, hessian: Array, linear: Array, rows: Array, bounds_lower: Array,
              bounds_upper: Array, *, hessian_changed: bool = True
              ) -> tuple[Array, bool, str, int]:
        """(z, optimal, status, iterations) of the QP with these matrices; ``optimal``:
        PIQP says it met its stopping criteria (the caller still checks z is finite)."""
        n = linear.shape[0]
        rows_f = np.asfortranarray(rows)
        z_min, z_max = bounds_lower[:n], bounds_upper[:n]
        lower, upper = bounds_lower[n:], bounds_upper[n:]
        if self._solver is None:
            solver = new_solver()
            solver.setup(hessian.T, linear, None, None, rows_f, lower, upper, z_min, z_max)
            self._solver = solver
        else:
            self._solver.update(P=hessian.T if hessian_changed else None, c=linear, G=rows_f,
                                h_l=lower, h_u=upper, x_l=z_min, x_u=z_max)
        status = self._solver.solve()
        result = self._solver.result
        return (np.array(result.x), status == piqp.PIQP_SOLVED, status.name,
                int(result.info.iter))
