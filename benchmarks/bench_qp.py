"""The local QP of a real step solved by our DAQP path and by CVXPY (issue 5).

    python benchmarks/bench_qp.py [--profile quick] [--out FILE]
    (or as the ``qp`` section of ``python benchmarks/run_all.py``)

The QPs are captured from a Case 2 run (in process, seed 0, 6 drones, M = 2, relaxed QP with
a collision row per drone within R_ca): every ``LocalQpWorkspace.solve`` call once the
barrier QP is active, with its inputs and the solution the agent got. The benchmark takes an
evenly spaced sample of those with an active constraint (a positive slack, or a row within
1e-6 of its bound) when there are enough, and solves every one of them by

- ours: ``LocalQpWorkspace.solve`` (one workspace, set up on the first QP and updated
  afterwards, as in an agent: rows written, DAQP update + solve, feasibility check);
- CVXPY rebuilt: ``cp.Variable``s, constraints and ``cp.Problem(...).solve()`` from scratch at
  every call, as the thesis did (``cvxpy_qp.solve_rebuilt``);
- CVXPY parametrized: one problem with ``cp.Parameter``s, new values and ``solve()`` per QP
  (``cvxpy_qp.ParametrizedQp``; its first solve, which compiles, is not timed),

with PIQP underneath (dense, tight tolerances) and also CLARABEL and OSQP. Each pass solves
every QP once by every method, interleaved in chunks of 10 QPs (so that the machine's load
falls on all methods alike); the table shows the median over the passes of each pass's
median and p99, the ratio to ours (by wall and by thread CPU time, which leaves out waiting
for a CPU on a loaded machine), and the largest ‖Δu‖ to our solution (the solutions must
agree for the comparison to be honest).
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import cvxpy as cp
import numpy as np
from common import (
    CONFIGS,
    PROFILES,
    Profile,
    SectionClock,
    fmt,
    fmt_spread,
    new_table,
    progress,
    report_section,
    section_parser,
    spread,
    stats,
)
from cvxpy_qp import ParametrizedQp, QpData, solve_rebuilt
from rich.table import Table
from rich.text import Text

from swarm.core import qp as qp_module
from swarm.core.qp import LocalQpWorkspace
from swarm.runs.reference import run_reference
from swarm.scenario.config import ScenarioConfig, load_config

SOLVERS = ("PIQP", "CLARABEL", "OSQP")
ACTIVE_TOLERANCE = 1e-6
CHUNK = 10  # QPs a method solves in a row before the next method's turn


@dataclasses.dataclass(frozen=True)
class CapturedQp:
    data: QpData
    z: np.ndarray  # what the agent's QP path returned in the run
    time_s: float  # sim time of the capture [s] (from the call order)

    @property
    def active(self) -> bool:
        """A slack in use or a row at its bound at the solution."""
        m, rows = self.data.m_targets, self.data.u_rows
        slack = np.concatenate((self.z[3:], np.zeros(rows.shape[0] - 2 * m)))
        gaps = rows @ self.z[:3] + slack - np.asarray(self.data.lower)
        return bool(np.any(self.z[3:] > ACTIVE_TOLERANCE) or np.any(gaps < ACTIVE_TOLERANCE))


@contextlib.contextmanager
def captured_qps(config: ScenarioConfig) -> Iterator[list[CapturedQp]]:
    """Record every ``LocalQpWorkspace.solve`` call (inputs and solution) while inside."""
    captured: list[CapturedQp] = []
    original = qp_module.LocalQpWorkspace.solve
    calls = [0]
    n = config.swarm.n_drones

    def solve(self: LocalQpWorkspace, nominal: tuple[float, float, float],
              u_columns: list[float], lower: list[float], weights: list[float],
              u_box: tuple[list[float], list[float]] | None = None) -> Any:
        if u_box is not None:
            raise ValueError("bench_qp captures the thesis' QP: no rate box "
                             "(command_accel_limit_m_s2 must be 0)")
        solution = original(self, nominal, u_columns, lower, weights)
        if solution.found:
            data = QpData(self.m_targets, len(lower) - 2 * self.m_targets,
                          tuple(float(v) for v in nominal), tuple(u_columns), tuple(lower),
                          tuple(weights), self.slack_weight, self.weight_floor, self.u_max)
            step = calls[0] // n + round(config.control.start_s / config.scenario.dt_s)
            captured.append(CapturedQp(data, solution.z.copy(),
                                       step * config.scenario.dt_s))
        calls[0] += 1
        return solution

    qp_module.LocalQpWorkspace.solve = solve  # type: ignore[method-assign]
    try:
        yield captured
    finally:
        qp_module.LocalQpWorkspace.solve = original  # type: ignore[method-assign]


def capture(profile: Profile) -> tuple[list[CapturedQp], dict[str, Any]]:
    """The sample of QPs to solve, and how it was drawn."""
    config = load_config(CONFIGS / "case2.toml").with_duration(profile.qp_capture_duration_s)
    if config.control.qp != "relaxed":
        raise ValueError("the comparison is written for Case 2's relaxed QP")
    with captured_qps(config) as everything:
        run_reference(config, seed=0)
    active = [q for q in everything if q.active]
    pool = active if len(active) >= profile.qp_count else everything
    picks = np.unique(np.linspace(0, len(pool) - 1, profile.qp_count).round().astype(int))
    chosen = [pool[i] for i in picks]
    info = {"captured": len(everything), "active": len(active), "sampled": len(chosen),
            "sampled_active": sum(q.active for q in chosen),
            "time_span_s": [min(q.time_s for q in chosen), max(q.time_s for q in chosen)],
            "shape": {"m_targets": chosen[0].data.m_targets,
                      "n_collision": [min(q.data.n_collision for q in chosen),
                                      max(q.data.n_collision for q in chosen)],
                      "variables": 3 + 2 * chosen[0].data.m_targets,
                      "rows": _span(len(q.data.lower) for q in chosen)}}
    return chosen, info


def _span(values: Iterable[int]) -> str:
    """"9" or "5-9": the values' range."""
    values = sorted(set(values))
    return str(values[0]) if len(values) == 1 else f"{values[0]}-{values[-1]}"


# -- the methods --------------------------------------------------------------------------


def ours(qps: list[CapturedQp]) -> Callable[[QpData], np.ndarray]:
    """Our path: one workspace per drone shape, as an agent holds it."""
    first = qps[0].data
    workspace = LocalQpWorkspace(first.m_targets, first.n_collision, relaxed=True,
                                 slack_weight=first.slack_weight, weight_floor=first.weight_floor,
                                 u_max=first.u_max)

    def solve(data: QpData) -> np.ndarray:
        solution = workspace.solve(data.nominal, list(data.u_columns), list(data.lower),
                                   list(data.weights))
        return solution.z

    return solve


def parametrized(qps: list[CapturedQp], solver: str) -> Callable[[QpData], np.ndarray]:
    first = qps[0].data
    # One shape for every QP: as many collision rows as the most any captured QP had.
    problem = ParametrizedQp(first.m_targets, max(q.data.n_collision for q in qps),
                             first.u_max, solver)
    problem.solve(first)  # compiles the problem; not timed
    return problem.solve


def methods(qps: list[CapturedQp]) -> dict[str, Callable[[QpData], np.ndarray]]:
    found: dict[str, Callable[[QpData], np.ndarray]] = {"ours (LocalQpWorkspace, DAQP)": ours(qps)}
    installed = set(cp.installed_solvers())
    for solver in SOLVERS:
        if solver not in installed:
            continue
        found[f"CVXPY rebuilt, {solver}"] = lambda data, s=solver: solve_rebuilt(data, s)
        found[f"CVXPY parametrized, {solver}"] = parametrized(qps, solver)
    return found


def time_pass(solvers: dict[str, Callable[[QpData], np.ndarray]], qps: list[CapturedQp],
              rotation: int) -> dict[str, tuple[list[float], list[float], list[np.ndarray]]]:
    """One solve of every QP by every method [µs, wall and thread CPU], interleaved in
    chunks of ``CHUNK`` QPs: each method solves a chunk in turn (starting from a different
    method each time), so a change in the machine's load falls on every method alike, while
    a method's solves still follow each other as an agent's do (one QP at a time would time
    ours right after CVXPY has swept the caches). Returns each method's wall times, CPU
    times and solutions."""
    names = list(solvers)
    out: dict[str, tuple[list[float], list[float], list[np.ndarray]]] = {
        n: ([], [], []) for n in names}
    gc.collect()
    for index, first in enumerate(range(0, len(qps), CHUNK)):
        shift = (index + rotation) % len(names)
        for name in names[shift:] + names[:shift]:
            solve, (times, cpu_times, solutions) = solvers[name], out[name]
            for q in qps[first:first + CHUNK]:
                start, cpu = time.perf_counter(), time.thread_time()
                try:
                    z = solve(q.data)
                except cp.SolverError:  # counted: a NaN solution, and the time it took
                    z = np.full_like(q.z, np.nan)
                times.append((time.perf_counter() - start) * 1e6)
                cpu_times.append((time.thread_time() - cpu) * 1e6)
                solutions.append(z)
    return out


def run(profile: Profile, step_result: dict[str, Any] | None = None) -> dict[str, Any]:
    clock = SectionClock()
    progress(f"qp: capturing QPs from {profile.qp_capture_duration_s:g} s of Case 2")
    qps, info = capture(profile)
    solvers = methods(qps)
    passes: list[dict[str, tuple[list[float], list[float], list[np.ndarray]]]] = []
    for rotation in range(profile.qp_passes):
        progress(f"qp: pass {rotation + 1}/{profile.qp_passes}: {len(qps)} QPs × "
                 f"{len(solvers)} methods")
        passes.append(time_pass(solvers, qps, rotation))
    reference_z = [q.z for q in qps]
    results = []
    for name in solvers:
        worst_du = worst_dz = 0.0
        for one in passes:
            for z, z_ref in zip(one[name][2], reference_z, strict=True):
                if np.isnan(z).any():
                    continue
                worst_du = max(worst_du, float(np.linalg.norm(z[:3] - z_ref[:3])))
                worst_dz = max(worst_dz, float(np.max(np.abs(z - z_ref))))
        timed = [stats(one[name][0]) for one in passes]
        cpu = [stats(one[name][1]) for one in passes]
        failures = sum(int(np.isnan(z).any()) for one in passes for z in one[name][2])
        results.append({
            "method": name, "passes": timed, "failed_solves": failures,
            "median_us": spread([p["median"] for p in timed]),
            "p99_us": spread([p["p99"] for p in timed]),
            "cpu_median_us": spread([p["median"] for p in cpu]),
            "max_du_norm": worst_du, "max_dz_abs": worst_dz})
    ours_median = results[0]["median_us"]["median"]
    ours_cpu = results[0]["cpu_median_us"]["median"]
    for res in results:
        median, cpu_median = res["median_us"]["median"], res["cpu_median_us"]["median"]
        res["ratio_to_ours"] = None if median is None or not ours_median else median / ours_median
        res["cpu_ratio_to_ours"] = (None if cpu_median is None or not ours_cpu
                                    else cpu_median / ours_cpu)
    return {"section": "qp", "profile": profile.name, "passes": profile.qp_passes,
            "sample": info, "results": results,
            "whole_step": whole_step_ratio(results, step_result), **clock.done()}


def whole_step_ratio(results: list[dict[str, Any]],
                     step_result: dict[str, Any] | None) -> dict[str, float] | None:
    """Our whole M = 2 step (everything included) against the same step with its qp section
    replaced by the CVXPY-rebuilt PIQP solve (medians), when the step section ran."""
    if step_result is None:
        return None
    ours_step = next((r for r in step_result["results"]
                      if r["m_targets"] == 2 and r["qp"] == "ours"), None)
    rebuilt = next((r for r in results if r["method"] == "CVXPY rebuilt, PIQP"), None)
    if ours_step is None or rebuilt is None or rebuilt["median_us"]["median"] is None:
        return None
    summary = ours_step["summary"]
    total = summary["total"]["median"]["median"]
    qp_section = summary["qp"]["median"]["median"]
    replaced = total - qp_section + rebuilt["median_us"]["median"]
    return {"ours_step_us": total, "ours_qp_section_us": qp_section,
            "cvxpy_rebuilt_us": rebuilt["median_us"]["median"],
            "step_with_cvxpy_us": replaced, "ratio": replaced / total}


def tables(result: dict[str, Any]) -> list[Table]:
    sample = result["sample"]
    shape = sample["shape"]
    table = new_table(
        f"Local QP of a real Case 2 step [µs]: {shape['variables']} variables, {shape['rows']} "
        f"rows; {sample['sampled']} QPs ({sample['sampled_active']} with an active "
        f"constraint) from t = {sample['time_span_s'][0]:.1f}-{sample['time_span_s'][1]:.1f} s",
        ["method", "median", "p99", "× ours", "CPU median", "× ours (CPU)", "max ‖Δu‖ to ours",
         "max |Δz|", "failed"],
        caption=(f"medians over {result['passes']} passes of each pass's median/p99 "
                 "(min–max over the passes); one solve per QP and method per pass, the "
                 f"methods interleaved in chunks of {CHUNK} QPs"))
    for res in result["results"]:
        ratio = res["ratio_to_ours"]
        cpu_ratio = res["cpu_ratio_to_ours"]
        table.add_row(res["method"], fmt_spread(res["median_us"]), fmt_spread(res["p99_us"]),
                      fmt(ratio, 1) if ratio is not None else "—",
                      fmt_spread(res["cpu_median_us"]),
                      fmt(cpu_ratio, 1) if cpu_ratio is not None else "—",
                      f"{res['max_du_norm']:.1e}", f"{res['max_dz_abs']:.1e}",
                      str(res["failed_solves"]))
    whole = result.get("whole_step")
    if whole:
        table.caption += Text(
            f"\nwhole M = 2 step: ours {whole['ours_step_us']:.0f} µs; with its qp section "
            f"({whole['ours_qp_section_us']:.0f} µs) replaced by the CVXPY-rebuilt PIQP solve "
            f"{whole['step_with_cvxpy_us']:.0f} µs = {whole['ratio']:.1f}×")
    return [table]


def main(argv: list[str] | None = None) -> int:
    parser = section_parser(__doc__, "qp.json")
    args = parser.parse_args(argv)
    return report_section(run(PROFILES[args.profile]), tables, "bench_qp.py", argv, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
