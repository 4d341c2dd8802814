"""Lockstep process-swarm throughput for N = 6, 12, 24, 48 drones (issues 5, 16).

    python benchmarks/bench_lockstep.py [--profile quick] [--out FILE]
    (or as the ``lockstep`` section of ``python benchmarks/run_all.py``)

Each run is a real process swarm (``SwarmLauncher``, mode lockstep: one ``sim-world``, N
``swarm-agent`` processes, Zenoh on loopback, MAVLink/UDP) of Case 2 scaled to N drones
(``swarm_configs``). Throughput is measured over the mission only, start-up excluded: from
the world's first "running" clock message (step 0) to its "done" (``swarm_probe``) —
simulated steps per wall second and the real-time factor (simulated s / wall s); the wall
time between consecutive steps (median and p99); CPU per agent process and of the world over
the same window, in cores (1.0 = one CPU busy). Also draws ``scaling.png`` (CPU per
simulated step against N, ``plot_scaling.py``) next to the JSON.
"""

from __future__ import annotations

from typing import Any

from common import (
    PROFILES,
    Profile,
    fmt,
    fmt_spread,
    new_table,
    over_runs,
    report_section,
    section_parser,
)
from plot_scaling import write_scaling_plot
from rich.table import Table
from swarm_probe import THREAD_GROUPS, swarm_section


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Median (and spread) over the repeats of each run's figures."""

    def over(get: Any) -> dict[str, Any]:
        return over_runs(runs, get)

    return {
        "sim_steps_per_s": over(lambda r: r["mission"]["sim_steps_per_s"]),
        "real_time_factor": over(lambda r: r["mission"]["real_time_factor"]),
        "step_period_ms_median": over(lambda r: r["mission"]["step_period_ms"]["median"]),
        "step_period_ms_p99": over(lambda r: r["mission"]["step_period_ms"]["p99"]),
        "agent_cores_median": over(lambda r: r["cpu"]["agent_cores"]["median"]),
        # CPU time an agent (the world) spends per simulated step [ms].
        "agent_cpu_ms_per_step": over(lambda r: 1e3 * r["cpu"]["agent_cores"]["median"]
                                      / r["mission"]["sim_steps_per_s"]),
        "world_cpu_ms_per_step": over(lambda r: 1e3 * r["cpu"]["world_cores"]
                                      / r["mission"]["sim_steps_per_s"]),
        "world_cores": over(lambda r: r["cpu"]["world_cores"]),
        # An agent's CPU per simulated step by thread group [ms] (swarm_probe.THREAD_GROUPS).
        **{f"agent_{group}_ms_per_step": over(
            lambda r, g=group: 1e3 * r["cpu"]["agent_thread_cores"][g]["median"]
            / r["mission"]["sim_steps_per_s"]) for group in THREAD_GROUPS},
        "total_cores": over(lambda r: r["cpu"]["total_cores"]),
        "step_us_median": over(lambda r: r["step_us"]["median"]),
        "step_us_p99": over(lambda r: r["step_us"]["p99"]),
        "launch_to_streaming_s": over(lambda r: r["startup"]["launch_to_streaming_s"]),
        "agent_hwm_mib_max": over(lambda r: r["memory_mib"]["agent_hwm"]["max"]),
        "violations": sum(len(r.get("violations", [])) for r in runs),
        "failed_runs": [{"error": r["error"], "usable": r["usable"]}
                        for r in runs if "error" in r],
    }


def run(profile: Profile) -> dict[str, Any]:
    return swarm_section("lockstep", profile.name, profile.lockstep_sizes, "lockstep",
                         profile.lockstep_duration_s, profile.lockstep_repeats, summarise)


def tables(result: dict[str, Any]) -> list[Table]:
    table = new_table(
        f"Lockstep process swarm, Case 2 scaled ({result['duration_s']:g} s simulated per run)",
        ["N", "sim steps/s", "real-time ×", "step wall ms med", "p99", "agent CPU ms/step",
         "world CPU ms/step", "total CPU cores", "agent step µs med", "p99",
         "launch→streaming s", "agent HWM MiB", "violations"],
        caption=(f"median (min–max) over {result['repeats']} runs; mission window only "
                 "(world's first 'running' clock message to 'done'); ms/step: CPU time per "
                 "simulated step (median agent; the world);\nagent step µs: the agents' own "
                 "step_us (compute only, QP active)"))
    for res in result["results"]:
        s = res["summary"]
        table.add_row(str(res["n_drones"]), fmt_spread(s["sim_steps_per_s"], 0),
                      fmt_spread(s["real_time_factor"], 2),
                      fmt_spread(s["step_period_ms_median"], 1),
                      fmt_spread(s["step_period_ms_p99"], 1),
                      fmt_spread(s["agent_cpu_ms_per_step"], 2),
                      fmt_spread(s["world_cpu_ms_per_step"], 2), fmt_spread(s["total_cores"], 2),
                      fmt(s["step_us_median"]["median"]),
                      fmt(s["step_us_p99"]["median"]),
                      fmt_spread(s["launch_to_streaming_s"], 1),
                      fmt(s["agent_hwm_mib_max"]["median"], 1), _violations(s))
    threads = new_table(
        "Where an agent's CPU goes in lockstep [ms per simulated step]",
        ["N", "agent total", "Python main thread", "Zenoh receive thread (+ our callbacks)",
         "other threads", "agent step µs (compute)"],
        caption=("median (min–max) over the runs of the median agent; main thread: the step, "
                 "MAVLink, encoding and publishing, waiting for the GIL is not CPU;\nreceive: "
                 "Zenoh's receive path (its app thread, session.ZENOH_RUNTIME_DEFAULT, or "
                 "rx threads) and our subscription callbacks (decode, validate, mailbox); "
                 "other: Zenoh's transmit thread, and the rest"))
    for res in result["results"]:
        s = res["summary"]
        threads.add_row(str(res["n_drones"]), fmt_spread(s["agent_cpu_ms_per_step"], 2),
                        *(fmt_spread(s[f"agent_{g}_ms_per_step"], 2) for g in THREAD_GROUPS),
                        f"{fmt(s['step_us_median']['median'])} µs")
    return [table, threads]


def _violations(summary: dict[str, Any]) -> str:
    """Invariant violations, and failed runs if any."""
    failed = summary["failed_runs"]
    if not failed:
        return str(summary["violations"])
    kept = sum(f["usable"] for f in failed)
    return f"{summary['violations']}; {len(failed)} run(s) failed, {kept} with figures kept"


def main(argv: list[str] | None = None) -> int:
    parser = section_parser(__doc__, "lockstep.json")
    args = parser.parse_args(argv)
    result = run(PROFILES[args.profile])
    code = report_section(result, tables, "bench_lockstep.py", argv, args.out)
    print(f"wrote {write_scaling_plot(result, args.out.with_name('scaling.png'))}")
    return code


if __name__ == "__main__":
    raise SystemExit(main())
