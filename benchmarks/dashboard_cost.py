"""CPU cost of the live dashboard during a real process swarm (six drones by default).

Runs ``launch-swarm``'s process swarm with the dashboard drawing to a terminal-like console
that writes to /dev/null, and prints the dashboard's own thread CPU time — rendering (the
refresh thread) and the telemetry callbacks (Zenoh's threads) — as a share of one core over
the mission's wall time.

    python benchmarks/dashboard_cost.py [CONFIG] [--mode realtime] [--duration 20]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from rich.console import Console

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.observe.dashboard import Dashboard, DashboardSettings
from swarm.scenario.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default=str(ROOT / "configs" / "case2.toml"))
    parser.add_argument("--mode", choices=("lockstep", "realtime"), default="realtime")
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--refresh-hz", type=float, default=4.0)
    parser.add_argument("--width", type=int, default=140)
    args = parser.parse_args()
    config = load_config(args.config).with_duration(args.duration)
    launcher = SwarmLauncher(LaunchOptions(
        config=config, config_path=str(Path(args.config).resolve()), seed=0, mode=args.mode),
        log=lambda line: print(line, file=sys.__stderr__))  # past the live redirect
    with open(os.devnull, "w", encoding="utf-8") as sink:
        console = Console(file=sink, force_terminal=True, width=args.width, height=60)
        dashboard = Dashboard(config, console,
                              settings=DashboardSettings(refresh_hz=args.refresh_hz))
        process_cpu, wall = time.process_time(), time.monotonic()
        with dashboard:
            launcher.run(on_progress=lambda step, _c: dashboard.advance(step),
                         telemetry_listeners=[dashboard.on_telemetry])
        process_cpu, wall = time.process_time() - process_cpu, time.monotonic() - wall
    stats = dashboard.stats
    print(f"{config.scenario.name}, {config.swarm.n_drones} drones, {args.mode}, "
          f"{args.duration:g} s simulated, dashboard up {wall:.1f} s wall")
    print(f"renders {stats.renders} ({stats.renders / wall:.2f} /s), "
          f"{1e3 * stats.render_cpu_s / max(stats.renders, 1):.2f} ms CPU each, "
          f"{100 * stats.render_cpu_s / wall:.2f} % of one core")
    print(f"telemetry {stats.telemetry_messages} messages, "
          f"{1e6 * stats.telemetry_cpu_s / max(stats.telemetry_messages, 1):.1f} µs CPU each, "
          f"{100 * stats.telemetry_cpu_s / wall:.3f} % of one core")
    print(f"whole launcher process: {100 * process_cpu / wall:.1f} % of one core "
          f"(collector, Zenoh, supervision and dashboard)")


if __name__ == "__main__":
    main()
