"""CPU cost of the live 3D view (``--foxglove``) to the launcher, a viewer connected.

Runs ``launch-swarm``'s process swarm (Case 2, realtime, by default) in this process, in
turns without and with the live view, and prints the launcher process's CPU time (every
thread: collector, Zenoh, supervision and, when on, the live view) as a share of one core
over the mission's wall time. With the view on, a Foxglove WebSocket client in a process of
its own (``tests/helpers/foxglove_client.py``, so its CPU is not counted) subscribes to
every channel; its message counts are printed to show the view was really fed. The cost is
the difference of the medians, measured side by side (off, on, off, on, …).

    python benchmarks/live_view_cost.py [CONFIG] [--duration 20] [--repeat 2] [--port 8799]

Needs the ``dev`` extra (``websockets``, for the client).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from swarm.launch.launcher import LaunchOptions, SwarmLauncher  # noqa: E402
from swarm.scenario.config import load_config  # noqa: E402

# The viewer: say "ready" once its imports are done, connect (retrying until the server is
# up), subscribe to everything, read until the server closes, print {topic: count} as JSON.
_CLIENT = """
import json, sys
from tests.helpers.foxglove_client import FoxgloveClient
print("ready", flush=True)
client = FoxgloveClient(sys.argv[1])
client.start(connect_timeout_s=60.0)
client.wait_closed(timeout_s=float(sys.argv[2]))
print(json.dumps({topic: len(items) for topic, items in client.messages.items()}))
"""


def one_run(config, config_path: str, port: int | None, duration_s: float
            ) -> tuple[float, float, dict[str, int]]:
    """(launcher CPU as a share of one core, wall time [s], the viewer's counts by topic)."""
    viewer = None
    if port is not None:
        viewer = subprocess.Popen(
            [sys.executable, "-c", _CLIENT, f"ws://127.0.0.1:{port}", str(4 * duration_s + 60)],
            cwd=ROOT, stdout=subprocess.PIPE, text=True)
        # Start the swarm only once the viewer is ready to connect: on a loaded machine its
        # start-up alone outlasted a short mission, and it joined a server about to close.
        if viewer.stdout is None or viewer.stdout.readline() != "ready\n":
            raise SystemExit("live_view_cost: the viewer did not start")
    launcher = SwarmLauncher(LaunchOptions(
        config=config, config_path=config_path, seed=0, mode="realtime",
        foxglove=None if port is None else ("127.0.0.1", port)),
        log=lambda line: print(line, file=sys.stderr))
    cpu, wall = time.process_time(), time.monotonic()
    launcher.run()
    cpu, wall = time.process_time() - cpu, time.monotonic() - wall
    counts: dict[str, int] = {}
    if viewer is not None:
        out, _ = viewer.communicate(timeout=60)
        if viewer.returncode != 0:
            raise SystemExit(f"live_view_cost: the viewer failed (exit {viewer.returncode})")
        counts = json.loads(out)
        if not counts:
            raise SystemExit("live_view_cost: the viewer got no message from the live view")
    return cpu / wall, wall, counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default=str(ROOT / "configs" / "case2.toml"))
    parser.add_argument("--duration", type=float, default=20.0, help="simulated seconds")
    parser.add_argument("--repeat", type=int, default=2, help="runs each way")
    parser.add_argument("--port", type=int, default=8799)
    args = parser.parse_args()
    config = load_config(args.config).with_duration(args.duration)
    path = str(Path(args.config).resolve())
    shares: dict[str, list[float]] = {"off": [], "on": []}
    print(f"{config.scenario.name}, {config.swarm.n_drones} drones, realtime, "
          f"{args.duration:g} s simulated, {args.repeat} runs each way, interleaved")
    for _ in range(args.repeat):
        for way in ("off", "on"):
            share, wall, counts = one_run(config, path, args.port if way == "on" else None,
                                          args.duration)
            shares[way].append(share)
            seen = ", ".join(f"{topic} {n}" for topic, n in sorted(counts.items())
                             if not topic.startswith("drone/"))
            plots = sum(n for topic, n in counts.items() if topic.startswith("drone/"))
            print(f"  view {way:3s}: launcher {100 * share:5.1f} % of one core over "
                  f"{wall:5.1f} s wall" + (f"; viewer got {seen}, plots {plots}" if counts
                                            else ""))
    off, on = statistics.median(shares["off"]), statistics.median(shares["on"])
    print(f"launcher CPU, median: view off {100 * off:.1f} %, on {100 * on:.1f} % of one core; "
          f"the live view costs {100 * (on - off):+.1f} % of one core")


if __name__ == "__main__":
    main()
