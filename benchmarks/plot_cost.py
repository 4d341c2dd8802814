"""Time to draw the thesis figures of a full-length run (``swarm-report --plots``).

Runs the scenario in process (Case 2 by default: 2500 steps × 6 drones × 2 targets), then
times ``write_plots`` on its record, ``--repeat`` times into fresh directories, and prints the
median and every figure written. The figures are a few seconds of work, not minutes.

    python benchmarks/plot_cost.py [CONFIG] [--duration S] [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from swarm.observe.plots import write_plots
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default=str(ROOT / "configs" / "case2.toml"))
    parser.add_argument("--duration", type=float, default=None,
                        help="simulated seconds (default: the config's)")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    config = load_config(args.config)
    if args.duration is not None:
        config = config.with_duration(args.duration)
    record = run_reference(config)
    times_s, written = [], []
    for _ in range(args.repeat):
        with tempfile.TemporaryDirectory(prefix="vigil-plots-") as out:
            started = time.perf_counter()
            written = write_plots(record, Path(out))
            times_s.append(time.perf_counter() - started)
    print(f"{config.scenario.name}: {record.n_steps} steps × {config.swarm.n_drones} drones × "
          f"{len(config.targets)} targets; {len(written)} figures "
          f"({', '.join(Path(p).name for p in written)})")
    print(f"write_plots: median {statistics.median(times_s):.2f} s over {args.repeat} "
          f"(min {min(times_s):.2f}, max {max(times_s):.2f})")


if __name__ == "__main__":
    main()
