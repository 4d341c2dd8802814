"""Realtime process swarm at 50 Hz for N = 6, 12, 24 drones (issue 3 point 6, issue 5).

    python benchmarks/realtime_swarm.py [--profile quick] [--sizes 6,12,24] [--duration S]
                                        [--repeats R] [--out FILE]
    python benchmarks/realtime_swarm.py --sizes 6 --duration 50    # full Case 2, 3 runs
    (or as the ``realtime`` section of ``python benchmarks/run_all.py``)

Each run is a real process swarm (``SwarmLauncher``, mode realtime: every loop at 50 Hz on
the wall clock with the newest data) of Case 2 scaled to N drones (``swarm_configs``).
Per run (``swarm_probe``):

- late-step rate: the agents' own counters (late steps / steps, ``collector.counters()``),
  over the whole mission and after each agent's first second (its start-up transient);
- step latency: the agents' ``step_us`` from telemetry (compute time of a step, barrier QP
  active), median and p99;
- neighbour-data age (end to end): ``counters.neighbour_age_ms`` from telemetry — the age of
  the freshest neighbour consensus message when a step uses it, counted from the neighbour's
  put (its Zenoh timestamp), so the hop through the router and the wait are both in it;
  median and p99;
- CPU per agent process (and the world's, and their total) over the mission window, in cores;
- the SPEC invariants and the final estimation errors, to see that the swarm still works.

A timing figure depends on the machine and its load: it is measured here, not asserted.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from common import (
    PROFILES,
    Profile,
    fmt_spread,
    new_table,
    over_runs,
    report_section,
    section_parser,
)
from rich.table import Table
from swarm_probe import swarm_section


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Median (and spread) over the repeats of each run's figures."""

    def over(get: Any) -> dict[str, Any]:
        return over_runs(runs, get)

    return {
        "late_fraction": over(lambda r: r["late_fraction"]),
        "late_fraction_after_1s": over(lambda r: r["late_fraction_after_1s"]),
        "step_us_median": over(lambda r: r["step_us"]["median"]),
        "step_us_p99": over(lambda r: r["step_us"]["p99"]),
        "neighbour_age_ms_median": over(lambda r: r["neighbour_age_ms"]["median"]),
        "neighbour_age_ms_p99": over(lambda r: r["neighbour_age_ms"]["p99"]),
        "agent_cores_median": over(lambda r: r["cpu"]["agent_cores"]["median"]),
        "world_cores": over(lambda r: r["cpu"]["world_cores"]),
        "total_cores": over(lambda r: r["cpu"]["total_cores"]),
        "stale_messages": over(lambda r: r["counters"]["stale_neighbour_messages"]),
        "final_error_max_m": over(lambda r: max(r["final_position_error_m"])),
        "violations": sum(len(r.get("violations", [])) for r in runs),
        "failed_runs": [{"error": r["error"], "usable": r["usable"]}
                        for r in runs if "error" in r],
    }


def run(profile: Profile) -> dict[str, Any]:
    return swarm_section("realtime", profile.name, profile.swarm_sizes, "realtime",
                         profile.realtime_duration_s, profile.realtime_repeats, summarise)


def tables(result: dict[str, Any]) -> list[Table]:
    table = new_table(
        f"Realtime process swarm at 50 Hz, Case 2 scaled ({result['duration_s']:g} s per run)",
        ["N", "late steps %", "late after 1 s %", "step µs med", "step µs p99",
         "nbr age ms med", "p99", "CPU/agent", "world CPU", "total CPU", "stale msgs",
         "max final err m", "violations"],
        caption=(f"median (min–max) over {result['repeats']} runs; late: agents' counters; "
                 "step µs: telemetry step_us (QP active); neighbour age: freshest neighbour "
                 "message at use, from the neighbour's put (hop included);\nCPU in cores over "
                 "the mission window"))
    for res in result["results"]:
        s = res["summary"]
        table.add_row(str(res["n_drones"]), fmt_spread(s["late_fraction"], 2, scale=100.0),
                      fmt_spread(s["late_fraction_after_1s"], 2, scale=100.0),
                      fmt_spread(s["step_us_median"]), fmt_spread(s["step_us_p99"]),
                      fmt_spread(s["neighbour_age_ms_median"], 1),
                      fmt_spread(s["neighbour_age_ms_p99"], 1),
                      fmt_spread(s["agent_cores_median"], 2), fmt_spread(s["world_cores"], 2),
                      fmt_spread(s["total_cores"], 2), fmt_spread(s["stale_messages"]),
                      fmt_spread(s["final_error_max_m"], 3), _violations(s))
    return [table]


def _violations(summary: dict[str, Any]) -> str:
    """Invariant violations, and failed runs if any."""
    failed = summary["failed_runs"]
    if not failed:
        return str(summary["violations"])
    kept = sum(f["usable"] for f in failed)
    return f"{summary['violations']}; {len(failed)} run(s) failed, {kept} with figures kept"


def main(argv: list[str] | None = None) -> int:
    parser = section_parser(__doc__, "realtime.json")
    parser.add_argument("--sizes", default=None, help="comma-separated N, e.g. 6,12,24")
    parser.add_argument("--duration", type=float, default=None, help="simulated s per run")
    parser.add_argument("--repeats", type=int, default=None)
    args = parser.parse_args(argv)
    profile = PROFILES[args.profile]
    if args.sizes:
        profile = dataclasses.replace(
            profile, swarm_sizes=tuple(int(v) for v in args.sizes.split(",")))
    if args.duration is not None:
        profile = dataclasses.replace(profile, realtime_duration_s=args.duration)
    if args.repeats is not None:
        profile = dataclasses.replace(profile, realtime_repeats=args.repeats)
    return report_section(run(profile), tables, "realtime_swarm.py", argv, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
