"""Realtime process swarm on this machine: late agent steps at 50 Hz (issue 3, point 6).

Run:  python benchmarks/realtime_swarm.py [--case case2] [--repeats 3]

Runs the full scenario as a realtime process swarm (world + N agents, 50 Hz wall clock)
``--repeats`` times, prints each run's counters and the median late-step rate, and writes
benchmarks/results/realtime_<case>.json. A timing figure depends on the machine and its load,
so it is measured here and quoted, not asserted by a unit test.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
from pathlib import Path

from swarm.checks import check_invariants, summarize_targets
from swarm.config import load_config
from swarm.launcher import LaunchOptions, SwarmLauncher

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default="case2")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--duration", type=float, default=None)
    args = parser.parse_args()
    path = ROOT / "configs" / f"{args.case}.toml"
    config = load_config(path)
    if args.duration:
        config = config.with_duration(args.duration)
    runs = []
    for repeat in range(args.repeats):
        launcher = SwarmLauncher(LaunchOptions(config=config, config_path=str(path), seed=0,
                                               mode="realtime"), log=lambda _line: None)
        record = launcher.run()
        counts = launcher.collector.counters()
        late = counts["late_steps"] / max(counts["agent_steps"], 1)
        targets = summarize_targets(record)
        run = {
            "repeat": repeat, **counts, "late_fraction": late,
            "violations": [str(v) for v in check_invariants(record)],
            "final_position_error_m": [t.final_position_error_m for t in targets],
            "min_lambda_bar_margin": [t.min_lambda_bar_margin for t in targets],
            "load_average": os.getloadavg(),
        }
        runs.append(run)
        print(f"run {repeat}: agent steps {counts['agent_steps']} (telemetry received "
              f"{counts['telemetry_received']}), late {counts['late_steps']} "
              f"({100 * late:.2f} %), stale {counts['stale_neighbour_messages']}, "
              f"violations {len(run['violations'])}, final errors "
              f"{[round(e, 3) for e in run['final_position_error_m']]}", flush=True)
    median = statistics.median(r["late_fraction"] for r in runs)
    print(f"median late-step rate over {len(runs)} runs: {100 * median:.2f} % (target ≤ 1 %)")
    out = ROOT / "benchmarks" / "results" / f"realtime_{args.case}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"case": args.case, "runs": runs, "median_late_fraction": median},
                              indent=2))


if __name__ == "__main__":
    main()
