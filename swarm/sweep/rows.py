"""One mission of a sweep as a task, and its result as one row of ``results.jsonl``. Pure: no
Dask, no files.

Every row has ``REQUIRED_KEYS``; the others (``swarm.sweep.spec.OPTIONAL_KEYS``) as the sweep
file's ``keep`` says. ``key`` identifies the point: a hash of the resolved config (the seed in
it), the seed, the mode, the fault injections and the code version, so a rerun of the same
sweep with the same code skips exactly the points whose rows are there.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from swarm.observe.report import RunReport
from swarm.sweep.spec import OPTIONAL_KEYS

OK, VIOLATED, FAILED = "OK", "VIOLATED", "FAILED"
REQUIRED_KEYS = ("key", "params", "axes", "seed", "mode", "verdict", "min_lambda_margin",
                 "min_distance_m", "exit_code", "wall_s", "reason", "code_version", "worker")
# Keys whose values differ between two runs of the same mission (timing, where it ran).
VARYING_KEYS = ("wall_s", "worker", "recording")


@dataclass(frozen=True)
class MissionTask:
    """Everything a worker needs to run one point (pickled to it by Dask)."""

    key: str
    params: dict[str, Any]  # the point's dotted keys → values
    axes: tuple[str, ...]  # which of them are grid axes
    seed: int
    mode: str  # "inprocess", "lockstep", "realtime", "sitl:ardupilot", "sitl:px4"
    config_data: dict[str, Any]  # the resolved, validated config (config_to_data)
    source: str  # the base scenario file, for the record's name
    code_version: str
    kill_agents: tuple[tuple[int, float], ...] = ()
    record_dir: str | None = None  # keep the recording there; None: not kept
    timeout_s: float | None = None
    stop_event: str | None = None  # the Dask Event whose setting stops the mission
    keep: tuple[str, ...] = OPTIONAL_KEYS


def mission_key(config_data: Mapping[str, Any], seed: int, mode: str,
                kill_agents: Sequence[tuple[int, float]], code_version: str) -> str:
    """The point's identity (hex, 20 digits): equal inputs, equal key, on any machine."""
    document = json.dumps({"config": config_data, "seed": seed, "mode": mode,
                           "kill_agents": [list(k) for k in kill_agents],
                           "code": code_version}, sort_keys=True, allow_nan=False,
                          separators=(",", ":"))
    return hashlib.sha256(document.encode()).hexdigest()[:20]


def _finite(value: float | None) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return float(value)


def _min(values: Sequence[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return min(known) if known else None


def _max(values: Sequence[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return max(known) if known else None


def base_row(task: MissionTask, *, verdict: str, exit_code: int | None, wall_s: float,
             reason: str, worker: str) -> dict[str, Any]:
    return {"key": task.key, "params": task.params, "axes": list(task.axes), "seed": task.seed,
            "mode": task.mode, "verdict": verdict, "min_lambda_margin": None,
            "min_distance_m": None, "exit_code": exit_code, "wall_s": round(wall_s, 3),
            "reason": reason, "code_version": task.code_version, "worker": worker}


def failed_row(task: MissionTask, reason: str, *, exit_code: int | None = None,
               wall_s: float = 0.0, worker: str = "") -> dict[str, Any]:
    """The row of a mission that crashed, timed out or never started: its reason, one line."""
    return base_row(task, verdict=FAILED, exit_code=exit_code, wall_s=wall_s,
                    reason=" ".join(reason.split()) or "failed (no reason given)", worker=worker)


def report_row(task: MissionTask, report: RunReport, *, exit_code: int | None, wall_s: float,
               reason: str = "", worker: str = "", recording: str | None = None,
               measures: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The row of a mission that ran: its report's verdict and figures, and ``measures``
    (a process mission's ``swarm.sweep.measures``). A report cut short (INCOMPLETE) is
    FAILED: nothing is known of the rest of the mission."""
    verdict = {"ok": OK, "violated": VIOLATED, "incomplete": FAILED}[report.verdict]
    if report.verdict == "incomplete" and not reason:
        reason = f"incomplete: {report.steps} of {report.coverage.planned_steps} steps"
    if report.violations and not reason:
        reason = "; ".join(str(v) for v in report.violations)
    row = base_row(task, verdict=verdict, exit_code=exit_code, wall_s=wall_s,
                   reason=" ".join(reason.split()), worker=worker)
    targets = report.targets
    row["min_lambda_margin"] = _min([t.min_lambda_bar_margin for t in targets])
    row["min_distance_m"] = report.min_pairwise_distance_m
    distance = report.min_pairwise_distance_m
    velocity = report.max_abs_velocity_mps
    margins: dict[str, float | None] = {
        "lambda": row["min_lambda_margin"],
        "true_lambda": _min([t.min_true_lambda_margin for t in targets]),
        "collision_m": None if distance is None else distance - report.collision_distance_m,
        "velocity_m_s": None if velocity is None else report.u_max_mps - velocity,
    }
    for kind, margin in report.envelope_margins_m.items():
        margins[f"envelope_{kind}_m"] = margin
    network = report.network
    if network is not None and network.keep != "none":
        margins["kept_link_m"] = network.min_kept_margin_m
    extra: dict[str, Any] = {
        "margins": margins,
        "violations": [{"invariant": v.invariant, "subject": v.subject or None,
                        "worst_value": _finite(v.worst_value), "limit": _finite(v.limit),
                        "excess": _finite(v.excess), "worst_time_s": _finite(v.worst_time_s),
                        "first_time_s": _finite(v.first_time_s)}
                       for v in report.violations],
        "min_true_lambda_margin": margins["true_lambda"],
        "final_error_m": _max([t.final_position_error_m for t in targets]),
        "rms_error_m": _max([t.rms_position_error_m for t in targets]),
        "lambda_copy_spread": _max([t.lambda_copy_spread for t in targets]),
        "max_abs_velocity_m_s": velocity,
        "qp_fallbacks": report.qp_fallbacks,
        "late_steps": report.late_steps,
        "rejected_messages": report.rejected_messages,
        "safety_conflicts": report.safety_conflicts,
        "split_s": None if network is None else network.first_split_s,
        "split_said_s": None if network is None else network.first_said_s,
        "min_lambda2": None if network is None else network.min_algebraic_connectivity,
        "link_conflicts": None if network is None else network.link_conflicts,
        "steps": report.steps,
        "planned_steps": report.coverage.planned_steps,
        "recording": recording,
    }
    extra.update(measures or {})
    row.update({key: value for key, value in extra.items() if key in task.keep})
    return row
