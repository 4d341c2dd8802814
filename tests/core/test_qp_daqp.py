"""The DAQP backend's own terms (``swarm.core.qp_daqp``): the names of DAQP's exit flags, the
settings it gives DAQP, and the arrays DAQP points into. What it solves, and how well, is
``tests/core/test_qp.py``'s (every backend runs those tests)."""

from __future__ import annotations

import gc
import weakref

import daqp
import numpy as np
import pytest

from swarm.core import qp_daqp


def _box_qp(u_max: float) -> tuple[np.ndarray, ...]:
    """(P, q, rows, bounds_lower, bounds_upper) of u_d = (1, 0) in the box |u_k| ≤ u_max, one
    row u_x ≥ −5, in the backend's bound form."""
    return (2.0 * np.eye(2), np.array([-2.0, 0.0]), np.array([[1.0, 0.0]]),
            np.array([-u_max, -u_max, -5.0]), np.array([u_max, u_max, np.inf]))


def test_every_exit_flag_has_its_daqp_name_and_an_unknown_one_its_number() -> None:
    """The status of a QpSolution names DAQP's exit flag (DAQP's own names, ``DAQP_`` and the
    flag's word); a flag this version does not list says its number, never None."""
    assert qp_daqp.status_name(1) == qp_daqp.SOLVED == "DAQP_OPTIMAL"
    assert qp_daqp.status_name(-1) == "DAQP_INFEASIBLE"
    assert qp_daqp.status_name(-5) == "DAQP_NONCONVEX"
    assert qp_daqp.status_name(0) == "DAQP_EXIT_0"
    assert qp_daqp.status_name(-99) == "DAQP_EXIT_-99"
    assert qp_daqp.status_name(7) == "DAQP_EXIT_7"


def test_daqp_is_given_the_backends_tolerance_and_iteration_limit(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """DAQP reads back, after set-up and after the set-up that follows a refused P, the primal
    tolerance and the iteration limit the backend sets (not DAQP's defaults 1e-6 and 1e4)."""
    created: list[daqp.Model] = []
    original = daqp.Model

    def recording() -> daqp.Model:
        created.append(original())
        return created[-1]

    monkeypatch.setattr(qp_daqp.daqp, "Model", recording)
    backend = qp_daqp.DaqpBackend()
    hessian, linear, rows, lower, upper = _box_qp(3.0)
    assert backend.solve(hessian, linear, rows, lower, upper)[1]
    assert backend.solve(hessian, linear, rows, lower, upper)[1]  # an update: no new model
    assert not backend.solve(np.diag([1.0, -1.0]), linear, rows, lower, upper)[1]
    assert backend.solve(hessian, linear, rows, lower, upper)[1]  # set up afresh
    assert len(created) == 2
    for model in created:
        settings = model.settings
        assert settings["primal_tol"] == qp_daqp.PRIMAL_TOLERANCE == 1e-12
        assert settings["iter_limit"] == qp_daqp.ITERATION_LIMIT == 1000


def test_the_arrays_daqp_points_into_stay_alive_until_the_next_solve() -> None:
    """DAQP keeps pointers into the arrays of a solve and reads them again at the next update,
    so a caller may pass temporaries (``QpSolver`` does): they stay alive after the call, and
    are let go once the next solve has replaced them."""
    backend = qp_daqp.DaqpBackend()
    for u_max in (3.0, 1.0):  # the set-up, then an update
        arrays = _box_qp(u_max)
        alive = [weakref.ref(a) for a in arrays]
        z, optimal, _, _ = backend.solve(*arrays)
        assert optimal
        np.testing.assert_allclose(z, [1.0, 0.0], atol=1e-12)
        del arrays
        gc.collect()
        assert all(ref() is not None for ref in alive), u_max
    backend.solve(*_box_qp(2.0))
    gc.collect()
    assert all(ref() is None for ref in alive)
