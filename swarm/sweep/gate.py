"""A sweep's gate (the sweep file's ``[gate]``): what its exit code holds it to. Pure.

The gate holds when no mission FAILED (a crash, a timeout, a run cut short says nothing of the
guarantee, so it is never let through), no mission broke one of the ``hard`` invariants (no
exception: one such row is enough), and every grid cell's pass rate OK / (OK + VIOLATED) is
at least ``min_pass_rate``. The floor is on the measured rate itself; its 95 % Wilson interval
is printed beside it to say how much the rate of that many missions can say.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from swarm.sweep.rows import FAILED
from swarm.sweep.spec import GateSpec
from swarm.sweep.stats import CellStats, describe_cell

MAX_LISTED = 10  # rows named one by one per kind of breach; the rest counted


@dataclass(frozen=True)
class GateVerdict:
    held: bool
    lines: tuple[str, ...]  # what was checked and what broke, one line each


def _mission(row: Mapping[str, Any]) -> str:
    params = " ".join(f"{k}={v}" for k, v in row.get("params", {}).items())
    return f"{params} seed {row.get('seed')}".strip()


def _listed(heads: list[str], what: str) -> list[str]:
    lines = heads[:MAX_LISTED]
    if len(heads) > MAX_LISTED:
        lines.append(f"gate: … and {len(heads) - MAX_LISTED} more {what}")
    return lines


def judge_gate(gate: GateSpec, rows: Sequence[Mapping[str, Any]],
               cells: Sequence[CellStats]) -> GateVerdict:
    """The gate over the sweep's ``rows`` and their ``cells`` (``swarm.sweep.stats``)."""
    lines: list[str] = []
    failed = [r for r in rows if r.get("verdict") == FAILED]
    breaches = []
    for row in rows:
        for violation in row.get("violations") or ():
            if violation.get("invariant") in gate.hard:
                subject = violation.get("subject") or ""
                worst = violation.get("worst_value")
                shown = "" if worst is None else f", worst {worst:.4g}"
                breaches.append(f"gate: {_mission(row)}: {violation['invariant']} broken "
                                f"({subject}{shown})")
    hard = ", ".join(gate.hard) or "none"
    lines.append(f"gate: hard invariants ({hard}): broken in {len(breaches)} place(s) over "
                 f"{len(rows)} missions")
    lines += _listed(breaches, "breaches")
    lines.append(f"gate: FAILED missions: {len(failed)}")
    lines += _listed([f"gate: {_mission(r)}: FAILED: {r.get('reason', '')}" for r in failed],
                     "FAILED missions")
    low_cells = 0
    for cell in cells:
        rate = cell.pass_rate
        low, high = cell.interval
        below = rate is None or rate < gate.min_pass_rate
        low_cells += below
        shown = "none judged" if rate is None else (
            f"{rate:.3f} ({cell.ok}/{cell.judged}, 95 % Wilson [{low:.3f}, {high:.3f}])")
        lines.append(f"gate: {describe_cell(cell.cell)}: pass rate {shown}, floor "
                     f"{gate.min_pass_rate:.3f}: {'BELOW' if below else 'held'}")
    held = not failed and not breaches and not low_cells
    lines.append(f"gate: {'HELD' if held else 'NOT HELD'}")
    return GateVerdict(held=held, lines=tuple(lines))
