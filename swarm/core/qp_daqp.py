"""The local QP's DAQP backend (``[control] qp_solver = "daqp"``, the default; SPEC §9).

DAQP is a dual active-set method: it ends on the active set of the optimum and solves its
equations, so z is the exact optimum up to round-off however large the slacks (u within
3.3e-9 m/s of a brute-force optimum with slack forces up to 1e9). The interface is the
one of ``swarm.core.qp.QpBackend``, and DAQP's own form is that interface's: ``bounds_lower``
= [z_min, lower] and ``bounds_upper`` = [z_max, +inf per row], the first n bound z, the rest
the rows.
"""

from __future__ import annotations

import daqp
import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

# A constraint counts as met when violated by at most PRIMAL_TOLERANCE (DAQP's default is
# 1e-6, which lets u sit up to ~1e-6/|row| off the optimum); the iteration limit is far above
# what these 7-variable QPs take (measured: at most 3 iterations on 60 active Case 2 QPs,
# each solved cold).
PRIMAL_TOLERANCE = 1e-12
ITERATION_LIMIT = 1000
SOLVED = "DAQP_OPTIMAL"
_EXIT_NAMES = {1: SOLVED, 2: "DAQP_SOFT_OPTIMAL", -1: "DAQP_INFEASIBLE", -2: "DAQP_CYCLE",
               -3: "DAQP_UNBOUNDED", -4: "DAQP_ITERLIMIT", -5: "DAQP_NONCONVEX",
               -6: "DAQP_OVERDETERMINED_INITIAL", -7: "DAQP_TIMELIMIT"}


def status_name(exit_flag: int) -> str:
    return _EXIT_NAMES.get(exit_flag, f"DAQP_EXIT_{exit_flag}")


class DaqpBackend:
    """One DAQP workspace for QPs of one shape: ``min ½zᵀPz + qᵀz`` s.t. ``z_min ≤ z ≤ z_max``
    and ``rows·z ≥ lower``. Set up on the first solve, updated after: DAQP keeps the active
    set of the last solve as its starting guess. DAQP reads the arrays it is given at each
    update (it holds on to them until the next one): the backend keeps a reference to them
    until then, so a caller may pass temporaries; it must not change them between solves."""

    solved_status = SOLVED

    def __init__(self) -> None:
        self._model: daqp.Model | None = None
        self._held: tuple[Array, ...] = ()  # what DAQP points into, alive until the next solve

    def solve(self, hessian: Array, linear: Array, rows: Array, bounds_lower: Array,
              bounds_upper: Array, *, hessian_changed: bool = True
              ) -> tuple[Array, bool, str, int]:
        """(z, optimal, status, iterations) of the QP with these matrices (C-contiguous);
        ``optimal``: DAQP says z is the optimum (the caller still checks z is finite)."""
        self._held = (hessian, linear, rows, bounds_lower, bounds_upper)
        if self._model is None:
            model = daqp.Model()
            exit_flag, _ = model.setup(hessian, linear, rows, bounds_upper, bounds_lower,
                                       np.zeros(bounds_upper.shape, dtype=np.intc))
            if exit_flag < 0:  # P not positive definite: nothing to solve with
                return np.full(linear.shape[0], np.nan), False, status_name(exit_flag), 0
            settings = model.settings
            settings["primal_tol"] = PRIMAL_TOLERANCE
            settings["iter_limit"] = ITERATION_LIMIT
            model.settings = settings
            self._model = model
        else:
            exit_flag = self._model.update(H=hessian if hessian_changed else None, f=linear,
                                           A=rows, bupper=bounds_upper, blower=bounds_lower)
            if exit_flag < 0:  # a new P that is not positive definite: not solved
                self._model = None  # set up afresh next time
                return np.full(linear.shape[0], np.nan), False, status_name(exit_flag), 0
        z, _objective, exit_flag, info = self._model.solve()
        return z, exit_flag == 1, status_name(exit_flag), int(info["iterations"])
