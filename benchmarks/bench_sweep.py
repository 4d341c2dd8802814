"""Sweeps (issue 42, point 9): what the sweep engine costs per mission, how two local workers
scale, and an in-process Case 2 mission with our QP against the thesis' CVXPY QP.

    python benchmarks/bench_sweep.py [--profile quick] [--out FILE]
    (or as the ``sweep`` section of ``python benchmarks/run_all.py``)

- overhead: K in-process Case 1 missions through ``swarm-sweep``'s own driver
  (``swarm.sweep.driver.run_sweep``: planning excluded, the client's connection, the Dask
  tasks, the rows written to ``results.jsonl`` included) on a local cluster of one worker
  process, started and warmed up (one mission) beforehand. The overhead per mission is the
  sweep's wall time less the missions' own (each row's ``wall_s``, measured in the worker),
  over K: scheduling, pickling, result handling. Issue 42's target: ≤ 5 % of a mission.
- scaling: the same K missions on a warm local cluster of two workers; one worker's wall time
  over two workers'. Target on 2 cores: ≥ 1.8×. Beside it the same missions on one and two
  plain processes (``ProcessPoolExecutor``, no Dask), run right after: what the machine gives
  two CPU-bound processes at that hour, the ceiling of the sweep's figure.
- cvxpy: Case 2 in-process (50 s simulated in the full profile) with our QP (DAQP, the
  agents' own), then the same mission with the QP built from nothing in CVXPY at every step
  as the thesis' simulations did (``cvxpy_qp.CvxpyRebuiltWorkspace``, PIQP underneath), one
  after the other in this process: the two wall times and their ratio.

Timings depend on the machine and its load (the section records both); nothing is asserted.
"""

from __future__ import annotations

import contextlib
import io
import logging
import tempfile
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
from common import (
    CONFIGS,
    PROFILES,
    Profile,
    SectionClock,
    fmt,
    new_table,
    progress,
    report_section,
    section_parser,
)
from cvxpy_qp import CvxpyRebuiltWorkspace
from rich.console import Console
from rich.table import Table

from swarm.runs import reference
from swarm.scenario.config import ScenarioConfig, load_config
from swarm.sweep.driver import new_stop_event, run_sweep
from swarm.sweep.plan import plan_sweep
from swarm.sweep.results import ResultsWriter

OVERHEAD_TARGET = 0.05  # of a mission
SCALING_TARGET = 1.8  # two local workers against one, on 2 cores


@contextlib.contextmanager
def local_cluster(workers: int) -> Iterator[str]:
    """A local Dask cluster of ``workers`` processes with one thread each (as swarm-sweep
    starts one); yields its scheduler's address."""
    from distributed import LocalCluster

    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address=":0", silence_logs=logging.ERROR)
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


def write_sweep(directory: Path, first_seed: int, count: int, duration_s: float) -> Path:
    path = directory / f"case1_{first_seed}.toml"
    path.write_text(f'base = "{CONFIGS / "case1.toml"}"\nseeds = [{first_seed}, '
                    f'{first_seed + count - 1}]\n[set]\n"scenario.duration_s" = {duration_s}\n')
    return path


def timed_sweep(address: str, directory: Path, first_seed: int, count: int,
                duration_s: float, name: str) -> dict[str, Any]:
    """One sweep of ``count`` Case 1 missions on the cluster at ``address``: its wall time
    and its rows' mission times."""
    out = directory / name
    plan = plan_sweep(write_sweep(directory, first_seed, count, duration_s), out)
    quiet = Console(file=io.StringIO(), width=160)
    with ResultsWriter(out) as writer:
        started = time.perf_counter()
        outcome = run_sweep(plan, writer, quiet, scheduler=address, workers=1,
                            stop_event=new_stop_event())
        wall = time.perf_counter() - started
    rows = outcome.rows
    failed = [r["reason"] for r in rows if r["verdict"] == "FAILED"]
    if len(rows) != count or failed:
        raise RuntimeError(f"sweep {name}: {len(rows)} rows of {count}; failed: {failed[:2]}")
    missions = [float(r["wall_s"]) for r in rows]
    return {"missions": count, "wall_s": wall, "mission_wall_s_sum": float(np.sum(missions)),
            "mission_wall_s_median": float(np.median(missions)),
            "workers": len({r["worker"] for r in rows})}


def case1_mission(seed: int, duration_s: float) -> float:
    """One in-process Case 1 mission in a plain process; its wall time."""
    config = load_config(CONFIGS / "case1.toml").with_duration(duration_s)
    started = time.perf_counter()
    reference.run_reference(config, seed=seed)
    return time.perf_counter() - started


def plain_processes(workers: int, count: int, duration_s: float) -> float:
    """The same missions on ``workers`` plain processes (no Dask), warm: the wall time. Two
    against one is what the machine itself gives two CPU-bound processes at that hour."""
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
        list(pool.map(case1_mission, range(10_000, 10_000 + workers), [duration_s] * workers))
        started = time.perf_counter()
        list(pool.map(case1_mission, range(count), [duration_s] * count))
        return time.perf_counter() - started


def sweep_figures(profile: Profile, directory: Path) -> dict[str, Any]:
    """The overhead (one worker) and the scaling (one against two workers) figures."""
    count, duration = profile.sweep_missions, profile.sweep_duration_s
    runs: dict[str, dict[str, Any]] = {}
    for workers in (1, 2):
        progress(f"sweep: {count} Case 1 missions ({duration:g} s) on {workers} local "
                 f"worker(s)")
        with local_cluster(workers) as address:
            timed_sweep(address, directory, 10_000, workers, duration, f"warm{workers}")
            runs[f"workers_{workers}"] = timed_sweep(address, directory, 0, count, duration,
                                                     f"run{workers}")
    progress("sweep: the same missions on 1 and 2 plain processes (the machine's own scaling)")
    plain = {f"workers_{w}_s": plain_processes(w, count, duration) for w in (1, 2)}
    one, two = runs["workers_1"], runs["workers_2"]
    overhead = (one["wall_s"] - one["mission_wall_s_sum"]) / count
    return {**runs,
            "overhead_per_mission_s": overhead,
            "overhead_fraction": overhead / one["mission_wall_s_median"],
            "speedup_2_workers": one["wall_s"] / two["wall_s"],
            "plain_processes": plain,
            "speedup_2_plain_processes": plain["workers_1_s"] / plain["workers_2_s"]}


@contextlib.contextmanager
def cvxpy_agents(config: ScenarioConfig) -> Iterator[None]:
    """The agents ``run_reference`` builds, each solving its relaxed QP by the CVXPY QP
    rebuilt at every call (a benchmark-only swap of the agent's private workspace)."""
    ctrl = config.control
    if ctrl.qp != "relaxed" or ctrl.command_accel_limit_m_s2:
        raise ValueError("the CVXPY mission is written for the relaxed QP without a rate box "
                         "(Case 2 on ideal vehicles)")
    original = reference.build_agent

    def build(*args: Any, **kwargs: Any) -> Any:
        agent = original(*args, **kwargs)
        agent._qp_relaxed = CvxpyRebuiltWorkspace(
            agent.setup.n_targets, agent.setup.n_drones - 1, slack_weight=ctrl.slack_weight,
            weight_floor=ctrl.weight_floor, u_max=ctrl.u_max_m_s)
        return agent

    reference.build_agent = build
    try:
        yield
    finally:
        reference.build_agent = original


def cvxpy_figures(profile: Profile) -> dict[str, Any]:
    """Case 2 in-process, our QP then the CVXPY QP rebuilt each step: wall times."""
    config = load_config(CONFIGS / "case2.toml")
    config = config.with_duration(profile.cvxpy_mission_duration_s) \
        if config.scenario.duration_s != profile.cvxpy_mission_duration_s else config
    out: dict[str, Any] = {"simulated_s": config.scenario.duration_s}
    # CVXPY's first solve in a process imports and sets up far more than the later ones.
    CvxpyRebuiltWorkspace(1, 1, slack_weight=1.0, weight_floor=1e-3, u_max=1.0).solve(
        (0.0, 0.0, 0.0), [0.0] * 9, [0.0, 0.0, -1.0], [1.0])
    for name in ("ours", "cvxpy"):
        progress(f"sweep: Case 2 in-process, {config.scenario.duration_s:g} s simulated, "
                 f"QP: {name}")
        with cvxpy_agents(config) if name == "cvxpy" else contextlib.nullcontext():
            started = time.perf_counter()
            record = reference.run_reference(config, seed=0)
            wall = time.perf_counter() - started
        out[name] = {"wall_s": wall, "qp_fallbacks": int(record.qp_fallback.sum()),
                     "final_positions_m": record.drone_positions_m[-1].tolist()}
    ours = np.asarray(out["ours"]["final_positions_m"])
    theirs = np.asarray(out["cvxpy"]["final_positions_m"])
    out["max_final_position_difference_m"] = float(np.abs(ours - theirs).max())
    out["ratio"] = out["cvxpy"]["wall_s"] / out["ours"]["wall_s"]
    return out


def run(profile: Profile) -> dict[str, Any]:
    clock = SectionClock()
    with tempfile.TemporaryDirectory(prefix="vigil-bench-sweep-") as name:
        sweep = sweep_figures(profile, Path(name))
    cvxpy = cvxpy_figures(profile)
    return {"profile": profile.name, "sweep": sweep, "cvxpy": cvxpy, **clock.done()}


def tables(result: dict[str, Any]) -> list[Table]:
    sweep, cvxpy = result["sweep"], result["cvxpy"]
    one, two = sweep["workers_1"], sweep["workers_2"]
    table = new_table("Sweeps: the engine's cost and scaling (in-process Case 1 missions)",
                      ["figure", "measured", "target"],
                      caption=f"{one['missions']} missions per sweep, warm local clusters")
    table.add_row("one worker: sweep wall / Σ mission wall", f"{fmt(one['wall_s'], 1)} s / "
                  f"{fmt(one['mission_wall_s_sum'], 1)} s", "")
    table.add_row("overhead per mission (scheduling, results)",
                  f"{fmt(1e3 * sweep['overhead_per_mission_s'], 1)} ms = "
                  f"{fmt(100 * sweep['overhead_fraction'], 1)} % of a mission "
                  f"({fmt(one['mission_wall_s_median'], 2)} s)",
                  f"≤ {100 * OVERHEAD_TARGET:g} %")
    table.add_row("two workers: sweep wall", f"{fmt(two['wall_s'], 1)} s", "")
    table.add_row("two workers against one", f"{fmt(sweep['speedup_2_workers'], 2)}×",
                  f"≥ {SCALING_TARGET:g}× on 2 cores")
    table.add_row("the same on plain processes, no Dask (the machine's own)",
                  f"{fmt(sweep['speedup_2_plain_processes'], 2)}×", "")
    qp = new_table("Case 2 in-process: our QP against the thesis' CVXPY QP rebuilt each step",
                   ["QP", "wall [s]", "QP fallbacks"],
                   caption=f"{cvxpy['simulated_s']:g} s simulated, seed 0; final positions "
                           f"agree to {cvxpy['max_final_position_difference_m']:.1e} m")
    qp.add_row("ours (DAQP)", fmt(cvxpy["ours"]["wall_s"], 2), str(cvxpy["ours"]["qp_fallbacks"]))
    qp.add_row("CVXPY rebuilt (PIQP)", fmt(cvxpy["cvxpy"]["wall_s"], 2),
               str(cvxpy["cvxpy"]["qp_fallbacks"]))
    qp.add_row("ratio", f"{fmt(cvxpy['ratio'], 1)}×", "")
    return [table, qp]


def main(argv: list[str] | None = None) -> int:
    args = section_parser(__doc__, "sweep.json").parse_args(argv)
    return report_section(run(PROFILES[args.profile]), tables, "bench_sweep.py", argv,
                          args.out)


if __name__ == "__main__":
    raise SystemExit(main())
