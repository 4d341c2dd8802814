"""How ``launch-swarm`` places its children for the scheduler (``launcher._placement``), and
which fault injections it accepts.

The world (physics and the mission clock) must not wait for CPU behind the agents: it gets
a session of its own, so Linux's per-session scheduling group (autogroup) gives it up to a
full share whatever the number of agents, while the agents share the launcher's session (a
session per agent gave the world 1/(N + 1) of the CPU). Every child leads a process group of
its own (stopped as one) and runs at the launcher's niceness.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.scenario.config import load_config

CASE1 = Path(__file__).resolve().parents[2] / "configs" / "case1.toml"


@pytest.mark.wallclock
def test_the_world_has_a_session_of_its_own_and_the_agents_share_the_launchers(
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
        assert pgid == pids[name], name
        assert nice == base, name
        if name == "world":
            assert sid == pids[name]  # its own session: it leads it
        else:
            assert sid == os.getsid(0), name


@pytest.mark.parametrize(("mode", "kills", "message"), [
    ("lockstep", ((1, 5.0),), "--kill-agent needs --mode realtime"),
    ("realtime", ((6, 5.0),), "no drone 6 (the swarm has 0..5)"),
    ("realtime", ((1, 31.0),), "within the mission (0, 30) s"),
    ("realtime", ((1, 0.0),), "within the mission"),
    ("realtime", ((1, 5.0), (1, 9.0)), "one kill per drone"),
])
def test_agent_kills_outside_the_mission_are_refused(mode: str, kills: tuple, message: str
                                                     ) -> None:
    """``--kill-agent``: a drone of the swarm, inside the mission, once, in realtime."""
    config = load_config(CASE1)
    with pytest.raises(ValueError, match=re.escape(message)):
        LaunchOptions(config=config, config_path=str(CASE1), seed=0, mode=mode,
                      kill_agents=kills)
