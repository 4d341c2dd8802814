"""A failed QP on disk (swarm.runs.failed_qp): saved, read back, solved again; bad files refused
in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from swarm.core.qp import QpSolver
from swarm.runs.failed_qp import FailedQpFileError, dump_name, load_failed_qp, main, save_failed_qp
from tests.helpers.qp_samples import infeasible_hard_qp


def test_a_saved_qp_reads_back_identical_and_fails_again_the_same_way(tmp_path: Path) -> None:
    failed = infeasible_hard_qp()
    path = save_failed_qp(failed, tmp_path / dump_name(failed))
    assert path.name == "qp-drone2-step41-hard.npz"
    loaded = load_failed_qp(path)
    assert (loaded.drone_id, loaded.step, loaded.attempt, loaded.status, loaded.iterations) == (
        2, 41, "hard", failed.status, failed.iterations)
    assert loaded.max_violation == failed.max_violation  # inf survives the round trip
    for name in ("cost_hessian", "cost_linear", "rows", "lower", "z_min", "z_max"):
        np.testing.assert_array_equal(getattr(loaded.qp, name), getattr(failed.qp, name))
    assert QpSolver().solve(loaded.qp).status == failed.status


def test_the_command_line_solves_a_saved_qp_again(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    failed = infeasible_hard_qp()
    path = save_failed_qp(failed, tmp_path / "q.npz")
    assert main([str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == failed.describe()
    assert out[1].startswith(f"solved again: {failed.status}") and "accepted: False" in out[1]
    assert main([]) == 2 and main([str(tmp_path / "missing.npz")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("usage:")
    assert err[1].startswith("failed_qp: ") and "missing.npz" in err[1]


def test_files_that_are_not_a_failed_qp_are_refused_in_one_line(tmp_path: Path) -> None:
    failed = infeasible_hard_qp()
    cases = {}
    cases["text"] = tmp_path / "text.npz"
    cases["text"].write_text("not a zip")
    cases["other npz"] = tmp_path / "other.npz"
    np.savez(cases["other npz"], x=np.zeros(3))
    cases["truncated"] = tmp_path / "truncated.npz"
    cases["truncated"].write_bytes(save_failed_qp(failed, tmp_path / "ok.npz").read_bytes()[:200])
    cases["wrong shapes"] = tmp_path / "shapes.npz"
    np.savez(cases["wrong shapes"], meta=np.array(
        '{"format": "vigil-failed-qp/1", "drone_id": 0, "step": 0, "attempt": "hard", '
        '"status": "x", "iterations": 1, "max_violation": "inf"}'),
        cost_hessian=np.eye(3), cost_linear=np.zeros(3), rows=np.zeros((2, 4)),
        lower=np.zeros(2), z_min=np.zeros(3), z_max=np.zeros(3))
    cases["other format"] = tmp_path / "format.npz"
    np.savez(cases["other format"], meta=np.array('{"format": "something/2"}'))
    for what, path in cases.items():
        with pytest.raises(FailedQpFileError) as err:
            load_failed_qp(path)
        message = str(err.value)
        assert message.startswith(str(path)) and "\n" not in message, (what, message)
