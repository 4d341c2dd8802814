"""How ``launch-swarm`` places its children for the scheduler (``launcher._placement``),
which fault injections it accepts, and how it reports every drone's end action.

The world (physics and the mission clock) must not wait for CPU behind the agents: it gets
a session of its own, so Linux's per-session scheduling group (autogroup) gives it up to a
full share whatever the number of agents, while the agents share the launcher's session (a
session per agent gave the world 1/(N + 1) of the CPU). Every child leads a process group of
its own (stopped as one) and runs at the launcher's niceness.
"""

from __future__ import annotations

import dataclasses
import os
import re
import signal
from pathlib import Path

import pytest

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.mavlink.link import EndReport
from swarm.messages.wire import TelemetryWire
from swarm.scenario.config import ScenarioConfig, load_config, write_resolved_config

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


# -- the end action of every drone ------------------------------------------------------------


def _with_vehicles(tmp_path: Path, duration_s: float, **vehicles: str
                   ) -> tuple[ScenarioConfig, Path]:
    """Case 1 with these ``[vehicles]`` settings, written where the children read it."""
    config = load_config(CASE1).with_duration(duration_s)
    config = dataclasses.replace(config, vehicles=dataclasses.replace(config.vehicles,
                                                                      **vehicles))
    return config, write_resolved_config(config, tmp_path / "config.json")


@pytest.mark.parametrize(("flavour", "action", "mode"), [
    ("ardupilot", "hold", "BRAKE"),  # ArduCopter's own mode names are pymavlink's
    ("px4", "rtl", "Return"),  # PX4's name of AUTO.RTL (pymavlink: "RTL")
    ("px4", "hold", "Hold"),  # PX4's name of AUTO.LOITER (pymavlink: "LOITER")
])
def test_every_drones_end_action_is_reported_as_its_autopilot_names_it(
        tmp_path: Path, flavour: str, action: str, mode: str) -> None:
    """Six drones on emulated vehicles of each flavour: the launcher reports the end action
    of all six (an ArduCopter SITL run once showed it for 2 of 6), from each agent's own
    account of it, with the mode named as the autopilot names it."""
    config, path = _with_vehicles(tmp_path, 2.0, flavour=flavour, end_action=action)
    lines: list[str] = []
    launcher = SwarmLauncher(LaunchOptions(config=config, config_path=str(path), seed=0,
                                           log_dir=tmp_path / "logs"), log=lines.append)
    launcher.run()
    drones = range(config.swarm.n_drones)
    assert launcher.end_actions == {i: EndReport(i, action, mode, "accepted")  # type: ignore[arg-type]
                                    for i in drones}
    assert f"launch-swarm: drones 0, 1, 2, 3, 4, 5: end action {action} ({mode}) accepted" \
        in lines, lines
    for i in drones:
        log = (tmp_path / "logs" / f"agent{i}.log").read_text()
        assert f"drone {i}: end action {action} ({mode}) accepted" in log.splitlines(), log


@pytest.mark.wallclock
def test_an_end_action_the_vehicles_do_not_answer_is_reported_for_every_drone(
        tmp_path: Path) -> None:
    """Realtime: once the mission runs, the world (which plays every vehicle) is stopped
    (SIGSTOP) and the launcher asked to stop: each agent commands its end action, twice,
    hears nothing, and says so; the launcher reports it for all six."""
    config, path = _with_vehicles(tmp_path, 30.0, flavour="ardupilot", end_action="land")
    lines: list[str] = []
    launcher = SwarmLauncher(LaunchOptions(config=config, config_path=str(path), seed=0,
                                           mode="realtime", log_dir=tmp_path / "logs"),
                             log=lines.append)

    def freeze_the_vehicles(telemetry: TelemetryWire) -> None:
        if telemetry.step >= 25 and not launcher.stop_requested.is_set():
            world = next(c for c in launcher.children if c.name == "world")
            os.kill(world.process.pid, signal.SIGSTOP)
            launcher.stop_requested.set()

    with pytest.raises(KeyboardInterrupt):
        launcher.run(telemetry_listeners=[freeze_the_vehicles])
    no_answer = "none within 1 s, twice; the vehicle keeps its own setpoint-loss failsafe"
    assert launcher.end_actions == {
        i: EndReport(i, "land", "LAND", "got no answer", no_answer)
        for i in range(config.swarm.n_drones)}, lines
    assert f"launch-swarm: drones 0, 1, 2, 3, 4, 5: end action land (LAND) got no answer: " \
           f"{no_answer}" in lines, lines
