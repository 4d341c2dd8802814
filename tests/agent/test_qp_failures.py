"""An agent's failed QPs (swarm.agent.qp_failures): the first few logged and saved, the rest
counted."""

from __future__ import annotations

from pathlib import Path

from swarm.agent.qp_failures import QpFailureLog
from swarm.runs.failed_qp import load_failed_qp
from tests.helpers.qp_samples import infeasible_hard_qp


def test_the_first_failures_are_logged_and_saved_then_counted(tmp_path: Path) -> None:
    lines: list[str] = []
    failures = QpFailureLog(lines.append, tmp_path, limit=3)
    for step in range(5):
        failures.report(infeasible_hard_qp(drone_id=1, step=step))
    assert failures.count == 5
    assert [p.name for p in failures.saved] == [f"qp-drone1-step{k}-hard.npz" for k in range(3)]
    assert len(lines) == 3 and lines[-1].endswith("; later ones are counted only")
    for k, (line, path) in enumerate(zip(lines, failures.saved, strict=True)):
        assert line.startswith(f"drone 1: step {k}: hard QP not solved: ") and str(path) in line
        assert load_failed_qp(path).step == k


def test_without_a_directory_or_when_it_cannot_be_written_they_are_only_logged(
        tmp_path: Path) -> None:
    lines: list[str] = []
    QpFailureLog(lines.append, None).report(infeasible_hard_qp())
    assert len(lines) == 1 and "saved" not in lines[0]
    lines.clear()
    failures = QpFailureLog(lines.append, tmp_path / "no" / "such" / "dir")
    failures.report(infeasible_hard_qp())
    assert failures.saved == [] and "; not saved (" in lines[0] and "\n" not in lines[0]
