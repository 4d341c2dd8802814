"""The PIQP backend's own terms (``swarm.core.qp_piqp``): the settings its solvers carry and
their silence. What it solves, and how well, is ``tests/core/test_qp.py``'s (every backend
runs those tests)."""

from __future__ import annotations

import numpy as np
import pytest

from swarm.core import qp_piqp


def test_a_new_solver_carries_the_backends_stopping_criteria() -> None:
    """PIQP reads back the residual and duality-gap tolerances and the iteration limit the
    backend sets (module docstring: the gap decides how close u gets to the optimum)."""
    settings = qp_piqp.new_solver().settings
    assert (settings.eps_abs, settings.eps_rel) == (qp_piqp.EPS_ABS, qp_piqp.EPS_REL)
    assert settings.check_duality_gap is True
    assert (settings.eps_duality_gap_abs, settings.eps_duality_gap_rel) == (
        qp_piqp.EPS_DUALITY_GAP_ABS, qp_piqp.EPS_DUALITY_GAP_REL)
    assert settings.max_iter == qp_piqp.ITERATION_LIMIT
    assert settings.verbose is False


def test_a_solve_writes_nothing(capfd: pytest.CaptureFixture[str]) -> None:
    """Each agent solves a QP every step: PIQP's banner and iteration log (its ``verbose``)
    would flood the agents' output, so a set-up, an update and their solves print nothing."""
    backend = qp_piqp.PiqpBackend()
    for u_max in (3.0, 1.0):
        z, optimal, status, _ = backend.solve(
            2.0 * np.eye(2), np.array([-2.0, 0.0]), np.array([[1.0, 0.0]]),
            np.array([-u_max, -u_max, -5.0]), np.array([u_max, u_max, np.inf]))
        assert optimal and status == qp_piqp.SOLVED
        np.testing.assert_allclose(z, [1.0, 0.0], atol=1e-8)
    assert capfd.readouterr() == ("", "")
