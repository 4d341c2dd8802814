"""How ``launch-swarm`` schedules its children on one host (realtime).

The world (physics and the mission clock) must never wait for CPU behind the agents: every
child shares the launcher's session, so Linux's per-session scheduling group (autogroup)
does not hand each agent the same share as the world, and realtime agents run
``AGENT_NICE`` nicer. Each child still leads a process group of its own (stopped as one).
"""

from __future__ import annotations

import os
from pathlib import Path

from swarm.config import load_config
from swarm.launcher import AGENT_NICE, LaunchOptions, SwarmLauncher

CASE1 = Path(__file__).resolve().parent.parent / "configs" / "case1.toml"


def test_realtime_agents_run_nicer_than_the_world_in_the_launchers_session(
        tmp_path: Path) -> None:
    config = load_config(CASE1).with_duration(2.0)
    launcher = SwarmLauncher(LaunchOptions(config=config, config_path=str(CASE1), seed=0,
                                           mode="realtime", log_dir=tmp_path),
                             log=lambda _line: None)
    seen: dict[str, tuple[int, int, int]] = {}

    def inspect(_telemetry) -> None:  # children are all up once telemetry flows
        if seen:
            return
        for child in launcher.children:
            pid = child.process.pid
            seen[child.name] = (os.getsid(pid), os.getpgid(pid),
                                os.getpriority(os.PRIO_PROCESS, pid))

    launcher.run(telemetry_listeners=[inspect])
    base = os.getpriority(os.PRIO_PROCESS, 0)
    assert set(seen) == {"world"} | {f"agent{i}" for i in range(config.swarm.n_drones)}
    pids = {child.name: child.process.pid for child in launcher.children}
    for name, (sid, pgid, nice) in seen.items():
        assert sid == os.getsid(0), name
        assert pgid == pids[name], name
        expected = min(base + AGENT_NICE, 19) if name.startswith("agent") else base
        assert nice == expected, (name, nice, expected)
