"""Every benchmark of issues 5 and 16 in one command: tables on stdout, JSON in results/.

    python benchmarks/run_all.py                   # full run (~25 min on 2 cores)
    python benchmarks/run_all.py --quick           # a few minutes, to benchmarks/results/quick/
    python benchmarks/run_all.py --only step,qp    # some sections

Sections (each also runs alone: ``python benchmarks/<module>.py``):

- ``host``     (bench_host.py)     the machine alone at this hour: Python's speed, what a
                                   wake-up between processes and a timer wake-up cost;
                                   measured again after the last section (``host_after``
                                   in the summary), so that a run's host is known at both
                                   ends;
- ``step``     (bench_step.py)     per-drone step for M = 1, 2, 3 with its breakdown and wire
                                   encode/decode, and the M = 2 step with the QP rebuilt in
                                   CVXPY;
- ``qp``       (bench_qp.py)       the local QP of real Case 2 steps: our DAQP path against
                                   CVXPY rebuilt and parametrized (PIQP, CLARABEL, OSQP);
- ``lockstep`` (bench_lockstep.py) process-swarm throughput for N = 6, 12, 24, 48, and
                                   scaling.png: CPU per step against N (plot_scaling.py);
- ``realtime`` (realtime_swarm.py) 50 Hz process swarm for N = 6, 12, 24: late steps, step
                                   latency, neighbour-data age, CPU per agent;
- ``startup``  (bench_startup.py)  launch → every drone streaming, agent memory, imports.
- ``sweep``    (bench_sweep.py)    swarm-sweep's overhead per in-process mission, two local
                                   workers against one, and in-process Case 2 with our QP
                                   against the CVXPY QP rebuilt each step (issue 42).
- ``camera``   (bench_camera.py)   the rendered camera (issue 45): cost per frame of each
                                   stage, accuracy and detection against range and angle,
                                   Case 1's six drones in lockstep and realtime at 50, 25
                                   and 10 frames per second beside the bearing camera.

Writes ``<out>/<section>.json`` and ``<out>/summary.json`` (machine, versions, load average
before and after each section, the issue's targets against the newest figures of every
section, those of sections not run this time read from their JSON). Nothing is asserted:
the figures depend on the machine and its load, which the summary records. Exit code 1 if a
section (or the host's second measurement) failed to run (its error is in the summary), else
0.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import bench_camera
import bench_host
import bench_lockstep
import bench_qp
import bench_startup
import bench_step
import bench_sweep
import realtime_swarm
from common import (
    PROFILES,
    RESULTS,
    SectionClock,
    console,
    fmt,
    load_average,
    machine_info,
    new_table,
    write_json,
)
from plot_scaling import WORLD_TARGET_MS_PER_DRONE, write_scaling_plot
from rich.table import Table

SECTIONS = ("host", "step", "qp", "lockstep", "realtime", "startup", "sweep", "camera")
MIB_PER_MB = 1e6 / 2**20


def run_section(name: str, profile: Any, done: dict[str, dict[str, Any]],
                out_dir: Path) -> dict[str, Any]:
    if name == "host":
        return bench_host.run(profile)
    if name == "step":
        return bench_step.run(profile)
    if name == "qp":  # the whole-step estimate takes the newest step figures
        step = done.get("step")
        if step is None and (out_dir / "step.json").exists():
            step = json.loads((out_dir / "step.json").read_text())
        return bench_qp.run(profile, step_result=step)
    if name == "lockstep":
        return bench_lockstep.run(profile)
    if name == "realtime":
        return realtime_swarm.run(profile)
    if name == "sweep":
        return bench_sweep.run(profile)
    if name == "camera":
        return bench_camera.run(profile)
    return bench_startup.run(profile)


TABLES: dict[str, Callable[[dict[str, Any]], list[Table]]] = {
    "host": bench_host.tables, "step": bench_step.tables, "qp": bench_qp.tables,
    "lockstep": bench_lockstep.tables, "realtime": realtime_swarm.tables,
    "startup": bench_startup.tables, "sweep": bench_sweep.tables,
    "camera": bench_camera.tables,
}


# -- the targets ------------------------------------------------------------------


def _swarm_figure(section: dict[str, Any] | None, n: int, key: str) -> float | None:
    if section is None:
        return None
    res = next((r for r in section["results"] if r["n_drones"] == n), None)
    return None if res is None else res["summary"][key]["median"]


def _world_ms_per_drone(lockstep: dict[str, Any] | None) -> tuple[float, int] | None:
    """The world's CPU per simulated step per drone at the largest N of the lockstep section
    (and that N): issue 16 bounds it up to N = 48."""
    if lockstep is None:
        return None
    for result in sorted(lockstep["results"], key=lambda r: -r["n_drones"]):
        value = result["summary"]["world_cpu_ms_per_step"]["median"]
        if value is not None:
            return value / result["n_drones"], int(result["n_drones"])
    return None


def targets(done: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Each target of issues 16 and 42 with the figure measured for it (None: section not
    run)."""
    step, startup, sweep = done.get("step"), done.get("startup"), done.get("sweep")
    step_m2 = cvxpy_ratio = cpu_ratio = None
    if step is not None:
        ours = next((r for r in step["results"] if r["m_targets"] == 2 and r["qp"] == "ours"),
                    None)
        step_m2 = None if ours is None else ours["summary"]["total"]["median"]["median"]
        ratio = step.get("cvxpy_step_ratio")
        cvxpy_ratio = None if ratio is None else ratio["total"]["median"]
        cpu_ratio = None if ratio is None else ratio["cpu"]["median"]
    rss = launch = None
    if startup is not None:
        rss = startup["summary"]["agent_hwm_mib_max"]["median"]
        launch = startup["summary"]["launch_to_streaming_s"]["median"]
    else:  # the lockstep N = 6 runs measure both as well
        rss = _swarm_figure(done.get("lockstep"), 6, "agent_hwm_mib_max")
        launch = _swarm_figure(done.get("lockstep"), 6, "launch_to_streaming_s")
    world = _world_ms_per_drone(done.get("lockstep"))
    rows = [
        ("per-drone step, M = 2, everything included (median)", "≤ 100 µs", step_m2,
         lambda v: v <= 100.0, lambda v: f"{v:.0f} µs"),
        ("the same step with the QP rebuilt in CVXPY is slower by (wall; thread CPU)",
         "≥ 50×", cvxpy_ratio, lambda v: v >= 50.0,
         lambda v: f"{v:.1f}×; {cpu_ratio:.1f}×" if cpu_ratio else f"{v:.1f}×"),
        ("lockstep N = 6 real-time factor", "≥ 8×",
         _swarm_figure(done.get("lockstep"), 6, "real_time_factor"),
         lambda v: v >= 8.0, lambda v: f"{v:.2f}×"),
        ("world CPU per simulated step, per drone, at the largest lockstep N",
         f"≤ {WORLD_TARGET_MS_PER_DRONE:g} ms", None if world is None else world[0],
         lambda v: v <= WORLD_TARGET_MS_PER_DRONE,
         lambda v: f"{v:.2f} ms (N = {world[1]})" if world else ""),
        ("realtime 50 Hz N = 12 late steps", "0 %",
         _swarm_figure(done.get("realtime"), 12, "late_fraction"),
         lambda v: v == 0.0, lambda v: f"{100 * v:.2f} %"),
        ("realtime 50 Hz N = 24 late steps", "≤ 1 %",
         _swarm_figure(done.get("realtime"), 24, "late_fraction"),
         lambda v: v <= 0.01, lambda v: f"{100 * v:.2f} %"),
        ("agent peak RSS (largest agent's VmHWM)", "≤ 150 MB", rss,
         lambda v: v / MIB_PER_MB <= 150.0,
         lambda v: f"{v:.1f} MiB = {v / MIB_PER_MB:.1f} MB"),
        ("launch of N = 6 → every drone streaming setpoints", "≤ 2 s", launch,
         lambda v: v <= 2.0, lambda v: f"{v:.2f} s"),
        ("sweep overhead per in-process Case 1 mission (issue 42)",
         f"≤ {100 * bench_sweep.OVERHEAD_TARGET:g} %",
         None if sweep is None else sweep["sweep"]["overhead_fraction"],
         lambda v: v <= bench_sweep.OVERHEAD_TARGET, lambda v: f"{100 * v:.1f} %"),
        ("sweep: 2 local workers against 1, in-process missions (issue 42)",
         f"≥ {bench_sweep.SCALING_TARGET:g}×",
         None if sweep is None else sweep["sweep"]["speedup_2_workers"],
         lambda v: v >= bench_sweep.SCALING_TARGET, lambda v: f"{v:.2f}×"),
    ]
    out = []
    for label, goal, value, ok, shown in rows:
        if value is None:
            status, text = "not measured", "—"
        else:
            status, text = ("met" if ok(value) else "not met"), shown(value)
        out.append({"target": label, "goal": goal, "value": value, "shown": text,
                    "status": status})
    return out


def targets_table(rows: list[dict[str, Any]]) -> Table:
    table = new_table("Issue 16 and 42 targets", ["target", "goal", "measured", "status"],
                      caption="medians over the repeats (see each section)")
    for row in rows:
        table.add_row(row["target"], row["goal"], row["shown"], row["status"])
    return table


def host_table(before: dict[str, Any], after: dict[str, Any]) -> Table:
    """The host's figures at the start and at the end of the run, side by side."""
    table = new_table("The host at both ends of this run", ["figure", "start", "end"],
                      caption=f"measured at {before['measured_at']} and {after['measured_at']}"
                              " (benchmarks/bench_host.py)")
    for (label, start), (_, end) in zip(bench_host.figure_rows(before),
                                        bench_host.figure_rows(after), strict=True):
        table.add_row(label, start, end)
    return table


def _load_line(clock: dict[str, Any]) -> str:
    cores = clock["cpu_cores"]
    return (f"load average {clock['load_before']} → {clock['load_after']}; CPU cores used by "
            f"us {cores['ours']:.2f}, by other processes {cores['others']:.2f}, stolen "
            f"{cores['steal']:.2f}")


# -- main ---------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few minutes instead of ~9")
    parser.add_argument("--profile", choices=sorted(PROFILES), default=None,
                        help="run sizes: full (default), quick (= --quick), smoke (tests)")
    parser.add_argument("--only", default=",".join(SECTIONS),
                        help=f"comma-separated sections of {', '.join(SECTIONS)}")
    parser.add_argument("--out", type=Path, default=None,
                        help="output directory (default benchmarks/results, or "
                             "benchmarks/results/quick with --quick)")
    args = parser.parse_args(argv)
    profile = PROFILES[args.profile or ("quick" if args.quick else "full")]
    chosen = [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = sorted(set(chosen) - set(SECTIONS))
    if unknown:
        parser.error(f"unknown sections {unknown}; choose from {', '.join(SECTIONS)}")
    out_dir = args.out or (RESULTS if profile.name == "full" else RESULTS / profile.name)
    out = console()
    machine = machine_info()
    out.print(f"benchmarks ({profile.name}): {', '.join(chosen)} on {machine['cpus']} CPUs "
              f"({machine['cpu_model']}), load average {load_average()}, commit "
              f"{machine['git_commit']}")
    clock = SectionClock()
    done: dict[str, dict[str, Any]] = {}
    sections_info: dict[str, Any] = {}
    for name in SECTIONS:
        if name not in chosen:
            continue
        out.print(f"[{time.strftime('%H:%M:%S')}] {name} ...", style="bold")
        try:
            result = run_section(name, profile, done, out_dir)
        except Exception as err:  # one broken section must not lose the others' figures
            out.print(f"{name}: failed: {type(err).__name__}: {err}", style="red")
            sections_info[name] = {"error": f"{type(err).__name__}: {err}"}
            continue
        result["finished_at"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        done[name] = result
        path = out_dir / f"{name}.json"
        write_json(path, {**result, "machine": machine})
        for table in TABLES[name](result):
            out.print(table)
        if name == "lockstep":
            out.print(f"wrote {write_scaling_plot(result, out_dir / 'scaling.png')}")
        sections_info[name] = {"json": str(path), "wall_s": result["wall_s"],
                               "load_before": result["load_before"],
                               "load_after": result["load_after"],
                               "cpu_cores": result["cpu_cores"]}
        out.print(f"{name}: {result['wall_s']:.0f} s; {_load_line(result)}; wrote {path}")
    # The targets take every section's newest figures: a section not run now comes from its
    # JSON of an earlier run in the same directory (said so in the summary).
    newest = dict(done)
    for name in SECTIONS:
        path = out_dir / f"{name}.json"
        if name not in newest and name not in sections_info and path.exists():
            earlier = json.loads(path.read_text())
            newest[name] = earlier
            sections_info[name] = {"json": str(path), "from_earlier_run": True,
                                   "finished_at": earlier.get("finished_at"),
                                   "machine": earlier.get("machine")}
    goals = targets(newest)
    out.print(targets_table(goals))
    host_after: dict[str, Any] | None = None
    if "host" in done:  # the host again, at the other end of the run
        try:
            host_after = bench_host.measure(profile)
        except Exception as err:  # the figures measured so far are kept all the same
            out.print(f"host (after): failed: {type(err).__name__}: {err}", style="red")
            host_after = {"error": f"{type(err).__name__}: {err}"}
        else:
            out.print(host_table(done["host"]["figures"], host_after))
    total = clock.done()
    summary = {"command": " ".join(["python", "benchmarks/run_all.py",
                                    *(argv if argv is not None else sys.argv[1:])]),
               "profile": profile.name, "machine": machine, **total,
               "sections": sections_info, "targets": goals, "host_after": host_after}
    write_json(out_dir / "summary.json", summary)
    out.print(f"total {fmt(total['wall_s'], 0)} s; {_load_line(total)}; wrote "
              f"{out_dir / 'summary.json'}")
    failed = any("error" in info for info in sections_info.values())
    return 1 if failed or (host_after is not None and "error" in host_after) else 0


if __name__ == "__main__":
    raise SystemExit(main())
