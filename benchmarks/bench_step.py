"""Per-drone step benchmark (issue 5): compute time of ``DroneAgent``'s step for M = 1, 2, 3.

Run from the repository root, in the project's virtualenv::

    python benchmarks/bench_step.py                 # 20 s per scenario, 3 repeats
    python benchmarks/bench_step.py --duration 10 --repeats 5 --out /tmp/step.json

Scenarios: Case 1 (M = 1, hard QP), Case 2 (M = 2, relaxed QP) and Case 2 with a third
target added in code (M = 3). Each is run in process by ``swarm.reference.run_reference``
(6 drones, seed 0); the numbers are the agents' own ``step_us`` (``begin_step`` +
``consensus_round`` × K + ``finish_step``, without waiting for neighbours) over every drone
and every step once the barrier QP is active (t ≥ ``control.start_s``), and the thread CPU
time of the same calls (which leaves out waiting for a CPU on a loaded machine). Per run:
median and p99; the table shows the median over the repeats of each, and the median per
section of the step (``DroneAgent.section_us``):

- estimation: the local ICF steps (V⁰/v⁰, posterior, prediction),
- consensus: the K rounds and the PI consensus / Gramian update,
- barrier: perception weights, HOCBF terms and the constraint rows,
- qp: writing the rows into the solver's matrices, PIQP update and solve, feasibility check
  (the PIQP column is update + solve alone, the agent's ``qp_solve_us``),
- other: input checks, messages and diagnostics.

Messaging encode/decode is not part of this in-process step (the process swarm's wire layer).

Timings are wall-clock (``time.perf_counter``): on a shared machine they include preemption,
so the load average before and after is printed and stored. The table goes to stdout and
everything to ``benchmarks/results/step.json`` (``--out``). ``PYTHONPATH=<other checkout>``
benchmarks another version of ``swarm`` (its sections only if it has ``section_us``).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import platform
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import piqp

import swarm
import swarm.reference as reference
from swarm.config import ScenarioConfig, TargetSection, load_config

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
DEFAULT_OUT = ROOT / "benchmarks" / "results" / "step.json"
SECTIONS = ("estimation", "consensus", "barrier", "qp", "other")


def three_target_config(case2: ScenarioConfig) -> ScenarioConfig:
    """Case 2 plus a third target: a line crossing between the other two."""
    third = TargetSection(trajectory="linear", start_m=(0.0, 0.8, 0.0),
                          velocity_m_s=(-0.1, 0.25, 0.0), ramp_s=5.0)
    return dataclasses.replace(case2, targets=(*case2.targets, third))


def scenarios(duration_s: float) -> list[tuple[str, int, ScenarioConfig]]:
    case1 = load_config(CONFIGS / "case1.toml").with_duration(duration_s)
    case2 = load_config(CONFIGS / "case2.toml").with_duration(duration_s)
    return [("case1 (hard QP)", 1, case1), ("case2 (relaxed QP)", 2, case2),
            ("case2 + 1 target", 3, three_target_config(case2))]


def _cpu_timed(agent, cpu_s: list[float]) -> None:
    """Wrap the agent's step methods to add their thread CPU time to ``cpu_s[0]`` (reset by
    ``begin_step``): unlike ``step_us`` (wall clock) it leaves out time the process waited
    for a CPU, which dominates on a loaded machine."""
    begin, rounds, finish = agent.begin_step, agent.consensus_round, agent.finish_step

    def begin_step(*args, **kwargs):
        start = time.thread_time()
        result = begin(*args, **kwargs)
        cpu_s[0] = time.thread_time() - start
        return result

    def consensus_round(*args, **kwargs):
        start = time.thread_time()
        result = rounds(*args, **kwargs)
        cpu_s[0] += time.thread_time() - start
        return result

    def finish_step(*args, **kwargs):
        start = time.thread_time()
        result = finish(*args, **kwargs)
        cpu_s[0] += time.thread_time() - start
        return result

    agent.begin_step, agent.consensus_round, agent.finish_step = (begin_step, consensus_round,
                                                                  finish_step)


@contextlib.contextmanager
def captured_agents() -> Iterator[list]:
    """Collect the agents ``run_reference`` builds (each with a CPU-time accumulator), to
    read their per-section and CPU timings."""
    agents: list = []
    original = reference.build_agent

    def build(*args, **kwargs):
        agent = original(*args, **kwargs)
        cpu_s = [0.0]
        _cpu_timed(agent, cpu_s)
        agents.append((agent, cpu_s))
        return agent

    reference.build_agent = build
    try:
        yield agents
    finally:
        reference.build_agent = original


def run_once(config: ScenarioConfig) -> dict:
    """One run: every control-active step of every drone."""
    step_us: list[float] = []
    cpu_us: list[float] = []
    piqp_us: list[float] = []
    sections: dict[str, list[float]] = {name: [] for name in SECTIONS}
    with captured_agents() as agents:

        def on_step(_k: int, diagnostics: list) -> None:
            for (agent, cpu_s), diag in zip(agents, diagnostics, strict=True):
                if not diag.control_active:
                    continue
                step_us.append(diag.step_us)
                cpu_us.append(cpu_s[0] * 1e6)
                piqp_us.append(diag.qp_solve_us)
                timing = getattr(agent, "section_us", None)
                if timing is not None:
                    for name in SECTIONS:
                        sections[name].append(timing[name])

        record = reference.run_reference(config, seed=0, on_step=on_step)
    steps = np.array(step_us)
    return {
        "median_us": float(np.median(steps)),
        "p99_us": float(np.percentile(steps, 99)),
        "mean_us": float(steps.mean()),
        "cpu_median_us": float(np.median(cpu_us)),
        "cpu_p99_us": float(np.percentile(cpu_us, 99)),
        "piqp_median_us": float(np.median(piqp_us)),
        "sections_median_us": ({name: float(np.median(v)) for name, v in sections.items()}
                               if sections["other"] else None),
        "samples": int(steps.size),
        "qp_fallbacks": int(record.qp_fallback.sum()),
        "wall_s": record.wall_time_s,
    }


def summarise(runs: list[dict]) -> dict:
    def median_of(key: str) -> float:
        return float(np.median([r[key] for r in runs]))

    sections = None
    if runs[0]["sections_median_us"] is not None:
        sections = {name: float(np.median([r["sections_median_us"][name] for r in runs]))
                    for name in SECTIONS}
    return {"median_us": median_of("median_us"), "p99_us": median_of("p99_us"),
            "cpu_median_us": median_of("cpu_median_us"), "cpu_p99_us": median_of("cpu_p99_us"),
            "piqp_median_us": median_of("piqp_median_us"), "sections_median_us": sections}


def table(results: list[dict]) -> str:
    header = (f"{'scenario':<20} {'M':>2} {'median':>8} {'p99':>8} {'cpu med':>8} "
              f"{'cpu p99':>8} {'PIQP':>7} "
              + " ".join(f"{name:>10}" for name in SECTIONS))
    lines = [header, "-" * len(header)]
    for res in results:
        s = res["summary"]
        parts = (" ".join(f"{s['sections_median_us'][name]:>10.0f}" for name in SECTIONS)
                 if s["sections_median_us"] else "  (no per-section timings in this version)")
        lines.append(f"{res['scenario']:<20} {res['m_targets']:>2} {s['median_us']:>8.0f} "
                     f"{s['p99_us']:>8.0f} {s['cpu_median_us']:>8.0f} {s['cpu_p99_us']:>8.0f} "
                     f"{s['piqp_median_us']:>7.0f} {parts}")
    lines.append("µs per drone step; median/p99: wall clock (the agent's step_us), cpu: thread "
                 "CPU time of the same calls;\nmedians over the repeats of each run's median or "
                 "p99; PIQP: update + solve; sections: median of each (wall clock)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0, help="simulated s per run")
    parser.add_argument("--repeats", type=int, default=3, help="runs per scenario")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON output")
    args = parser.parse_args(argv)

    load_before = os.getloadavg()
    started = time.perf_counter()
    results = []
    for label, m_targets, config in scenarios(args.duration):
        runs = [run_once(config) for _ in range(args.repeats)]
        results.append({"scenario": label, "m_targets": m_targets, "runs": runs,
                        "summary": summarise(runs)})
    load_after = os.getloadavg()
    print(table(results))
    print(f"load average (1/5/15 min) before {load_before[0]:.2f}/{load_before[1]:.2f}/"
          f"{load_before[2]:.2f}, after {load_after[0]:.2f}/{load_after[1]:.2f}/"
          f"{load_after[2]:.2f} on {os.cpu_count()} CPUs; {time.perf_counter() - started:.0f} s")
    report = {
        "command": " ".join(["python", "benchmarks/bench_step.py", *(argv or sys.argv[1:])]),
        "swarm_package": str(Path(swarm.__file__).resolve().parent),
        "duration_s": args.duration, "repeats": args.repeats,
        "machine": {"cpus": os.cpu_count(), "load_before": load_before,
                    "load_after": load_after, "python": platform.python_version(),
                    "numpy": np.__version__, "piqp": piqp.__version__,
                    "processor": platform.processor() or platform.machine()},
        "results": results,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
